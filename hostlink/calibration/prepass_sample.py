"""Which part of a session the calibration's pre-pass (:mod:`hostlink.calibration.robust`) looks at: at most
:data:`PREPASS_MAX_FRAMES` evenly spaced frames, and in them at most :data:`PREPASS_MAX_PAIRS` star pairs."""

from __future__ import annotations

import numpy as np

#: Pre-pass: most frames it looks at (evenly spaced through the session): at 10-30 stars per frame ~5x10^4 long pairs
#: and 10^4 triples settle the scale to ~1e-5 (1.003393 against 1.003387 from 1000 frames of seed 004's benchmark
#: session; the voting tolerance is 3 % and the fit refines it) and the parity beyond doubt, and the pre-pass costs
#: the same for 10^3 or 10^6 frames (a third of what 1000 frames cost).
PREPASS_MAX_FRAMES = 300


def prepass_frames(n_frames: int, max_frames: int = PREPASS_MAX_FRAMES) -> np.ndarray:
    """Indices (sorted, unique) of the at most ``max_frames`` evenly spaced frames (by default those the pre-pass
    uses, :data:`PREPASS_MAX_FRAMES`)."""
    if n_frames <= max_frames:
        return np.arange(n_frames, dtype=np.int64)
    return np.unique(np.linspace(0, n_frames - 1, max_frames).round().astype(np.int64))


#: Pre-pass: most star pairs it forms over all its frames (its pair table is held for the scale's iterations, the vote
#: and the triples: ~56 bytes a pair at its peak, so ~450 MB here). Every frame's pairs are n (n - 1) / 2: a session of
#: large frames (4574 identified stars a frame, a 16 Mpx 40-deg render) held 10^7 pairs a frame, 2.9 GB for 5 frames
#: and ~25 GB for 50 (docs/realsky.md "Large frames"). Above it each frame keeps evenly spaced rows, as many in every
#: frame as fit; the real sets' sessions (granasat 3.3 M pairs, the rendered 50-deg set 5.1 M) are below it, unchanged.
PREPASS_MAX_PAIRS = 8_000_000


def prepass_rows(frame_starts: np.ndarray, max_pairs: int = PREPASS_MAX_PAIRS) -> np.ndarray | None:
    """The rows the pre-pass keeps so its frames hold at most ``max_pairs`` star pairs (:data:`PREPASS_MAX_PAIRS`):
    None when all of them fit; else a row mask keeping, in each frame of more than N rows, N evenly spaced ones (its
    first and last among them), N the largest cap whose pairs fit (at least 3: a triple for the parity)."""
    counts = np.diff(np.asarray(frame_starts, dtype=np.int64))

    def pairs(cap: int) -> int:
        n = np.minimum(counts, cap)
        return int(np.sum(n * (n - 1) // 2))

    if counts.size == 0 or pairs(int(counts.max())) <= max_pairs:
        return None
    low, high = 3, int(counts.max())  # pairs(low) fits or low is the floor; pairs(high) does not
    while high - low > 1:
        mid = (low + high) // 2
        low, high = (mid, high) if pairs(mid) <= max_pairs else (low, mid)
    keep = np.zeros(int(frame_starts[-1]), dtype=bool)
    for start, n in zip(np.asarray(frame_starts[:-1], dtype=np.int64), counts, strict=True):
        if n <= low:
            keep[start : start + n] = True
        else:
            keep[start + np.unique(np.linspace(0, n - 1, low).round().astype(np.int64))] = True
    return keep
