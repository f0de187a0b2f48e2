"""``hostlink identify`` shows progress over the frames (its rounds take seconds to minutes on a real session, and
printed nothing until the end): the command passes :func:`hostlink.api.identify_iteratively`'s per-frame
``progress`` to the progress bar, the session's frames its total (the bar, ``hostlink.progress``, is silent when
stderr is no terminal)."""

from dataclasses import replace

import numpy as np

from hostlink.cli import main
from hostlink.files.session import write_session
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate


def test_the_command_drives_a_progress_bar_over_the_frames(tmp_path, recorded_progress):
    sim = simulate(SimConfig(camera=seed004_camera(), frames=3, noise_px=0.05, min_stars=10, maglim=6.5, seed=2))
    blind = replace(sim.session, star_id=np.zeros_like(sim.session.star_id), ra_deg=None, dec_deg=None)
    path = tmp_path / "blind.csv"
    write_session(path, blind)
    shown = recorded_progress
    out = tmp_path / "out.csv"
    assert (
        main(["identify", str(path), "--nominal", "builtin:seed004_nominal", "--out", str(out), "--rounds", "1"]) == 0
    )
    assert shown == [("identifying frames", 3, True, [1, 2, 3])]
    args = ["identify", str(path), "--nominal", "builtin:seed004_nominal", "--out", str(out), "--rounds", "1"]
    assert main([*args, "--quiet"]) == 0 and main([*args, "--json"]) == 0
    assert [enabled for _, _, enabled, _ in shown[1:]] == [False, False]
