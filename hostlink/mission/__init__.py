"""The main job, ``hostlink bench`` (docs/architecture.md: hostlink/mission): the whole mission end to end against an
emulated sensor.

* :mod:`~hostlink.mission.config`: what a run is given (:class:`BenchConfig`, the built-in true camera, the nominal);
* :mod:`~hostlink.mission.run`: the run, phase by phase (simulate, stream, calibrate, upload, track);
* :mod:`~hostlink.mission.summary`: what it produced (:class:`BenchRun`) as ``summary.json`` and the terminal table;
* :mod:`~hostlink.mission.plots`: the report's PNG plots;
* :mod:`~hostlink.mission.example`: ``hostlink example``, the worked session's input files.
"""
