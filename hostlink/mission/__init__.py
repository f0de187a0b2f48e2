"""The main job, ``hostlink bench`` (ARCHITECTURE.md: hostlink/mission): the whole mission end to end against an
emulated sensor, its summary and its plots."""
