"""The C firmware core measured on emulated Cortex-M processors (``hostlink costs --target``, docs/port-kit.md
section 7): a simulated session and an upload driven through :mod:`hostlink.portkit.target_costs`."""

from __future__ import annotations

#: Frames per star count of ``hostlink costs --target`` (each update's instructions are within 1 % frame to frame).
TARGET_COST_FRAMES = 4


def target_costs(targets: list[str], frames: int = TARGET_COST_FRAMES, progress=None, optimise: str = "O2") -> list:
    """The C firmware core measured on emulated Cortex-M processors (``hostlink costs --target``;
    hostlink.portkit.target_costs): a seed-004 session simulated with at least 32 stars per frame (Hp <= 8) is
    replayed through the target's estimator at 8, 16 and 32 stars, an upload of a refined set through its firmware.
    Needs the ``cortexm`` extra (a one-line UserError otherwise)."""
    from hostlink.errors import UserError
    from hostlink.files.params import BUILTIN_PREFIX, load_params
    from hostlink.portkit import cortexm
    from hostlink.portkit import target_costs as tc
    from hostlink.sky.references import session_references
    from hostlink.sky.simulate import SimConfig, seed004_camera, simulate

    if not 1 <= int(frames) <= 1000:
        raise UserError(f"--frames must be 1..1000, got {frames}")
    chosen = [cortexm.target(t) for t in targets]
    cortexm.require_tools()
    cfg = SimConfig(
        camera=seed004_camera(), frames=int(frames), noise_px=0.05, min_stars=32, max_stars=40, maglim=8.0, seed=28
    )
    session = simulate(cfg).session
    refs = session_references(session)
    rows = [(session.x_px[r], session.y_px[r], refs.r[r], refs.usable[r]) for r in session.frame_slices()]
    nominal = load_params(BUILTIN_PREFIX + "seed004_nominal")
    refined = seed004_camera()  # the upload: the true camera as a refined set
    return [tc.measure_target(t, nominal, refined, rows, progress, optimise) for t in chosen]
