#!/usr/bin/env python
"""A new camera, tried as a user would (issue 30): the shared real sets through the documented commands
(``hostlink centroid`` -> ``hostlink identify`` -> ``hostlink calibrate``, each a separate process), with the nominal
wrong and the images in the other forms a user's camera writes them, and bad input that must fail in one line.

    PYTHONPATH=. .venv/bin/python scripts/newcamera.py [--set granasat|openstartracker] [--root DIR] [--cases a,b]

Cases (each against the unperturbed run, "base"):

- nominal: focal length 8 % short (``f0.92``) and 8 % long (``f1.08``); the principal point 30 px off in x and y
  (``pp30``); the time given as a date instead of ``--time-unknown`` where the set has one (``dated``);
- images: 16-bit FITS and 16-bit TIFF (counts x 257: the 8-bit range stretched), RGB PNG (the grey frame in three
  channels), flipped left-right (a mirrored detector: the parity must be reported, the nominal's principal point
  mirrored), rotated 180 deg (principal point rotated), turned 90 deg (``rot90``: width and height swapped in the
  nominal, the principal point turned), 2 x 2 binned (the sum of four pixels in a 16-bit FITS with its SATURATE,
  the nominal at twice the pixel pitch and the principal point at (x0 - 0.5) / 2);
- bad input (``bad``): a fisheye nominal, the other set's nominal (another detector size than the session's
  images), a corrupt image, an empty file, an image of zeros, a nominal that identifies nothing, no time at all:
  each must exit non-zero with one line on stderr and no traceback, and write no output file.

Per case: frames and stars identified (the detected stars; the faint ones admitted at predicted places beside),
the stars named in both this run and the base (matched by position, mapped back to the original pixel grid, within
1 px) and how many of them are named differently, the calibrated focal length against the base's and the calibrated
residual (RMS px, in the case's own pixels). Prints a Markdown table (docs/realsky.md, "A new camera").
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: The directory holding the image sets (docs/realsky.md): not in the repository, named by the environment or --root.
ROOT = Path(os.environ["STARTRACKER_REALSKY_ROOT"]) if "STARTRACKER_REALSKY_ROOT" in os.environ else None


@dataclass(frozen=True)
class ImageSet:
    pattern: str
    nominal: dict
    centroid_args: tuple[str, ...]
    date: str | None  # a UTC date the frames were taken on, if known


SETS = {
    # the source repository's own nominal (docs/realsky.md)
    "granasat": ImageSet(
        "*.jpg",
        {
            "focal_length_mm": 2657.33 * 4.65e-3,
            "pixel_pitch_um": 4.65,
            "principal_point_px": [666.0, 440.0],
            "image_size_px": [1280, 960],
        },
        (),
        None,
    ),
    # scripts/realsky.py's nominal and centroiding (median of the frames, 3 sigma)
    "openstartracker": ImageSet(
        "img*.png",
        {
            "focal_length_mm": 85.0,
            "pixel_pitch_um": 6.45,
            "principal_point_px": [695.5, 519.5],
            "image_size_px": [1392, 1040],
        },
        ("--median-of-inputs", "--threshold-sigma", "3"),
        "2018-05-09",
    ),
}

#: Matching radius between a case's centroid (mapped back) and the base's [original px].
MATCH_PX = 1.0


def hostlink(args: list[str]) -> subprocess.CompletedProcess:
    """One ``hostlink`` command as its own process (what a user runs)."""
    code = "import sys; from hostlink.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, check=False)


# ---------------------------------------------------------------------------------------------------------------
# image forms: each writes the frames in its form and says how its pixels map back to the original grid


def _write_fits(path: Path, pixels: np.ndarray, saturate: float | None = None) -> None:
    from astropy.io import fits

    hdu = fits.PrimaryHDU(pixels.astype(np.uint16))
    if saturate is not None:
        hdu.header["SATURATE"] = saturate
    hdu.writeto(path, overwrite=True)


def _write_tiff(path: Path, pixels: np.ndarray) -> None:
    import tifffile

    tifffile.imwrite(path, pixels.astype(np.uint16))


def _write_png(path: Path, pixels: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(pixels).astype(np.uint8)).save(path)


#: Counts per ADU of the 16-bit forms: 255 x 257 = 65535, the 16-bit clip level at the 8-bit one; the 8-bit file's
#: grey (a colour file's mean of three channels, a multiple of 1/3) is kept to 0.5 / 257 ADU.
SCALE_16 = 257.0
#: Counts per ADU of the binned FITS: the sum of four pixels (at most 1020) x 64 fits 16 bits (SATURATE 65280).
SCALE_BIN = 64.0


def form_writer(form: str):
    """(suffix, write(path, grey [ADU], the file's own pixel array), to_original(x, y, width, height)) of one image
    form (``width, height``: the form's own image size, its nominal's ``image_size_px``). Every form is lossless (to
    the rounding stated at its scale): a flip or rotation moves the file's own pixels, RGB keeps a colour file's
    channels (a grey file's level in all three)."""
    same = lambda x, y, w, h: (x, y)  # noqa: E731
    if form == "fits16":
        return ".fits", lambda p, g, raw: _write_fits(p, np.rint(g * SCALE_16)), same
    if form == "tiff16":
        return ".tif", lambda p, g, raw: _write_tiff(p, np.rint(g * SCALE_16)), same
    if form == "rgb":
        return ".png", lambda p, g, raw: _write_png(p, raw if raw.ndim == 3 else np.repeat(raw[:, :, None], 3, 2)), same
    if form == "flip":
        return ".png", lambda p, g, raw: _write_png(p, raw[:, ::-1]), lambda x, y, w, h: (w - 1 - x, y)
    if form == "rot180":
        return ".png", lambda p, g, raw: _write_png(p, raw[::-1, ::-1]), lambda x, y, w, h: (w - 1 - x, h - 1 - y)
    if form == "rot90":  # np.rot90 turns counter-clockwise: the form's pixel (x, y) is the original's (h - 1 - y, x)
        return ".png", lambda p, g, raw: _write_png(p, np.rot90(raw)), lambda x, y, w, h: (h - 1 - y, x)
    if form == "bin2":

        def write(p, g, raw):
            h, w = (g.shape[0] // 2) * 2, (g.shape[1] // 2) * 2
            b = g[:h, :w].reshape(h // 2, 2, w // 2, 2).sum(axis=(1, 3))
            _write_fits(p, np.rint(b * SCALE_BIN), saturate=4 * 255.0 * SCALE_BIN)

        # binned pixel centre i covers original pixels 2i and 2i + 1: x = 2 x_bin + 0.5
        return ".fits", write, lambda x, y, w, h: (2 * x + 0.5, 2 * y + 0.5)
    raise ValueError(form)


def form_nominal(form: str, nominal: dict) -> dict:
    """The nominal a user would write for the transformed camera."""
    x0, y0 = nominal["principal_point_px"]
    w, h = nominal["image_size_px"]
    if form == "flip":
        return dict(nominal, principal_point_px=[w - 1 - x0, y0])
    if form == "rot180":
        return dict(nominal, principal_point_px=[w - 1 - x0, h - 1 - y0])
    if form == "rot90":
        return dict(nominal, principal_point_px=[y0, w - 1 - x0], image_size_px=[h, w])
    if form == "bin2":
        return dict(
            nominal,
            pixel_pitch_um=nominal["pixel_pitch_um"] * 2,
            principal_point_px=[(x0 - 0.5) / 2, (y0 - 0.5) / 2],
            image_size_px=[w // 2, h // 2],
        )
    return nominal


def write_form(images: list[Path], form: str, out: Path) -> list[Path]:
    from PIL import Image

    from hostlink.images.read import read_image

    suffix, write, _ = form_writer(form)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for image in images:
        target = out / (image.stem + suffix)
        with Image.open(image) as raw:
            write(target, read_image(image).pixels, np.asarray(raw))
        paths.append(target)
    return paths


# ---------------------------------------------------------------------------------------------------------------
# one run of the chain


@dataclass
class Run:
    case: str
    ok: bool
    message: str = ""
    frames: int = 0
    frames_identified: int = 0
    stars: int = 0
    faint: int = 0
    parity: str = ""
    focal_mm: float = float("nan")
    residual_px: float = float("nan")
    calibrated_stars: int = 0
    rows: dict | None = None  # frame -> (x, y, star_id, faint) arrays in the original grid


def _rows(path: Path, to_original, size) -> dict:
    from hostlink.files.session import read_session

    s = read_session(path)
    extra = s.extra or {}
    snr = np.array([float(v) if str(v).strip() else np.nan for v in extra.get("snr", [""] * len(s))])
    x, y = to_original(np.asarray(s.x_px, float), np.asarray(s.y_px, float), *size)
    out = {}
    for f in np.unique(s.frame):
        m = s.frame == f
        out[int(f)] = (x[m], y[m], np.asarray(s.star_id)[m], np.isfinite(snr[m]))
    return out


def run_chain(case: str, paths: list[Path], nominal: dict, centroid_args, work: Path, to_original) -> Run:
    work.mkdir(parents=True, exist_ok=True)
    nominal_path = work / "nominal.json"
    nominal_path.write_text(json.dumps(nominal))
    cent, ident, cal = work / "c.csv", work / "i.csv", work / "cal.json"
    steps = [
        ("centroid", [*map(str, paths), *centroid_args, "--quiet", "--out", str(cent)]),
        (
            "identify",
            [str(cent), "--nominal", str(nominal_path), "--report", str(work / "r.json"), "--out", str(ident)],
        ),
        ("calibrate", [str(ident), "--nominal", str(nominal_path), "--quiet", "--out", str(cal)]),
    ]
    note = ""
    for name, args in steps:
        p = hostlink([name, *args])
        if p.returncode and name == "calibrate" and "mirrored" in p.stderr:
            # what the error says to do: flip x in the session (and the nominal's principal point with it)
            note = "calibrated after x flipped, as calibrate's error on the mirrored session asks"
            args = _flipped_for_calibrate(ident, nominal, work)
            p = hostlink([name, *args])
        if p.returncode:
            return Run(case, False, f"{name}: exit {p.returncode}: {p.stderr.strip().splitlines()[-1:]}")
    report = json.loads((work / "r.json").read_text())
    result = json.loads(cal.read_text())
    rows = _rows(ident, to_original, nominal["image_size_px"])
    faint = sum(int(np.count_nonzero((sid > 0) & fa)) for _, _, sid, fa in rows.values())
    return Run(
        case,
        True,
        note,
        frames=report["frames"],
        frames_identified=report["frames_identified"],
        stars=report["stars_identified"],
        faint=faint,
        parity=str(report.get("parity")),
        focal_mm=result["focal_length_mm"],
        residual_px=result["residuals"]["after"]["rms_px"],
        calibrated_stars=result["residuals"]["after"]["n_stars"],
        rows=rows,
    )


def _flipped_for_calibrate(ident: Path, nominal: dict, work: Path) -> list[str]:
    """``calibrate``'s arguments for the identified session with x -> width - 1 - x and the nominal to match."""
    from dataclasses import replace

    from hostlink.files.session import read_session, write_session
    from hostlink.images.identify import flipped_x_camera
    from onboard.params import params_from_dict, params_to_dict

    width = nominal["image_size_px"][0]
    s = read_session(ident)
    write_session(work / "i_flipped.csv", replace(s, x_px=(width - 1) - s.x_px))
    (work / "nominal_flipped.json").write_text(json.dumps(params_to_dict(flipped_x_camera(params_from_dict(nominal)))))
    return [
        str(work / "i_flipped.csv"),
        "--nominal",
        str(work / "nominal_flipped.json"),
        "--quiet",
        "--out",
        str(work / "cal.json"),
    ]


def compare(run: Run, base: Run, radius_px: float = MATCH_PX) -> tuple[int, int]:
    """(stars named in both runs at the same place, of them named differently)."""
    both = differ = 0
    for f, (x, y, sid, _) in run.rows.items():
        if f not in base.rows:
            continue
        bx, by, bsid, _ = base.rows[f]
        named, bnamed = sid > 0, bsid > 0
        if not named.any() or not bnamed.any():
            continue
        d2 = (x[named, None] - bx[None, bnamed]) ** 2 + (y[named, None] - by[None, bnamed]) ** 2
        j = np.argmin(d2, axis=1)
        near = d2[np.arange(len(j)), j] <= radius_px**2
        both += int(near.sum())
        differ += int(np.count_nonzero(sid[named][near] != bsid[bnamed][j[near]]))
    return both, differ


# ---------------------------------------------------------------------------------------------------------------
# bad input


def bad_input_cases(images: list[Path], image_set: ImageSet, work: Path) -> list[tuple[str, str]]:
    """Each bad input through the command it reaches: (case, what happened). A case passes when the command exits
    non-zero, prints one line on stderr and no traceback, and writes no output."""
    work.mkdir(parents=True, exist_ok=True)
    good = work / "good.csv"
    hostlink(["centroid", str(images[0]), "--time-unknown", "--quiet", "--out", str(good)])
    nominal = image_set.nominal
    w, h = nominal["image_size_px"]
    half_diag_mm = 0.5 * np.hypot(w, h) * nominal["pixel_pitch_um"] * 1e-3
    fisheye = dict(nominal, focal_length_mm=half_diag_mm / np.tan(np.radians(80.0)))  # 160 deg across the diagonal
    wrong = dict(nominal, focal_length_mm=nominal["focal_length_mm"] * 2.5)
    (work / "fisheye.json").write_text(json.dumps(fisheye))
    (work / "wrong.json").write_text(json.dumps(wrong))
    other = next(s.nominal for s in SETS.values() if s.nominal["image_size_px"] != nominal["image_size_px"])
    (work / "other.json").write_text(json.dumps(other))
    corrupt = work / "corrupt.jpg"
    corrupt.write_bytes(images[0].read_bytes()[:2000])
    garbage = work / "garbage.png"
    garbage.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 8)
    empty = work / "empty.png"
    empty.write_bytes(b"")
    zeros = work / "zeros.png"
    _write_png(zeros, np.zeros((h, w)))
    cases = {
        "fisheye nominal": ["identify", str(good), "--nominal", str(work / "fisheye.json")],
        "nominal 2.5 x long": ["identify", str(good), "--nominal", str(work / "wrong.json")],
        "another camera's nominal": ["identify", str(good), "--nominal", str(work / "other.json")],
        "truncated JPEG": ["centroid", str(corrupt), "--time-unknown"],
        "garbage PNG": ["centroid", str(garbage), "--time-unknown"],
        "empty file": ["centroid", str(empty), "--time-unknown"],
        "image of zeros": ["centroid", str(zeros), "--time-unknown"],
        "no time known": ["centroid", str(images[0])],
    }
    results = []
    for name, args in cases.items():
        out = work / (name.replace(" ", "_").replace(",", "") + ".out")
        p = hostlink([*args, "--out", str(out)])
        lines = [line for line in p.stderr.strip().splitlines() if line.strip()]
        traceback = "Traceback" in p.stderr
        verdict = "ok" if p.returncode and not traceback and len(lines) == 1 and not out.exists() else "FAILS THE RULE"
        results.append(
            (
                name,
                f"exit {p.returncode}, {len(lines)} line(s), output written: {out.exists()}, "
                f"{'traceback' if traceback else 'no traceback'}: {verdict}: {lines[-1] if lines else ''}",
            )
        )
    return results


# ---------------------------------------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--set", choices=sorted(SETS), default="granasat")
    parser.add_argument("--root", type=Path, default=ROOT)
    parser.add_argument("--cases", default="base,f0.92,f1.08,pp30,dated,fits16,tiff16,rgb,flip,rot180,rot90,bin2,bad")
    parser.add_argument("--work", type=Path, default=None, help="keep the files here (default: a temporary folder)")
    a = parser.parse_args()
    if a.root is None:
        raise SystemExit(
            "the real frames are not in the repository: set STARTRACKER_REALSKY_ROOT or --root (docs/realsky.md)"
        )
    image_set = SETS[a.set]
    images = sorted((a.root / a.set).glob(image_set.pattern))
    if not images:
        raise SystemExit(f"{a.root / a.set}: no {image_set.pattern} (set STARTRACKER_REALSKY_ROOT)")
    cases = a.cases.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        work = a.work or Path(tmp)
        time_args = ("--time-unknown",)
        same = form_writer("fits16")[2]
        base = run_chain("base", images, image_set.nominal, (*image_set.centroid_args, *time_args), work / "base", same)
        runs = [base]
        for case in cases:
            if case in ("base", "bad"):
                continue
            nominal, paths, to_original, args = image_set.nominal, images, same, image_set.centroid_args + time_args
            if re.fullmatch(r"f[0-9.]+", case):
                nominal = dict(nominal, focal_length_mm=nominal["focal_length_mm"] * float(case[1:]))
            elif case == "pp30":
                x0, y0 = nominal["principal_point_px"]
                nominal = dict(nominal, principal_point_px=[x0 + 30.0, y0 + 30.0])
            elif case == "dated":
                if image_set.date is None:
                    continue
                args = (*image_set.centroid_args, "--date", image_set.date)
            else:
                paths = write_form(images, case, work / case / "images")
                nominal, to_original = form_nominal(case, nominal), form_writer(case)[2]
            runs.append(run_chain(case, paths, nominal, args, work / case, to_original))
            print(f"{case}: done", file=sys.stderr, flush=True)
        print(
            "| case | frames | stars (+ faint) | parity | named in both with the base | named differently "
            "| f / base's f | residual [px] |"
        )
        print("|---|---:|---:|---|---:|---:|---:|---:|")
        for r in runs:
            if not r.ok:
                print(f"| {r.case} | failed: {r.message} | | | | | | |")
                continue
            both, differ = compare(r, base) if r is not base and base.ok else (0, 0)
            scale = r.focal_mm / base.focal_mm if base.ok else float("nan")
            case = f"{r.case} ({r.message})" if r.message else r.case
            print(
                f"| {case} | {r.frames_identified} of {r.frames} | {r.stars} (+ {r.faint}) | {r.parity} | "
                f"{both} | {differ} | {scale:.5f} | {r.residual_px:.3f} ({r.calibrated_stars}) |"
            )
        if "bad" in cases:
            print()
            for name, what in bad_input_cases(images, image_set, work / "bad"):
                print(f"- {name}: {what}")


if __name__ == "__main__":
    main()
