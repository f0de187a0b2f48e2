"""``hostlink identify``: lost-in-space identification of a session's unidentified stars (issue 11).

Parses the options, calls :func:`hostlink.images.identify.identify_session` (the method and its checks are there),
writes the session through the one session writer and prints one line per frame.
"""

from __future__ import annotations

import argparse

from hostlink.commands.jsonopt import add_json_argument

HELP = "identify a session's unidentified stars (star_id 0) against Hipparcos, lost in space"
DESCRIPTION = (
    "Identify the rows of SESSION.csv with star_id 0 (centroids from `hostlink centroid`, or a sensor's raw "
    "telemetry) against the bundled Hipparcos catalogue, frame by frame, with no attitude known. Tolerates a "
    "nominal focal length off by up to 10 %, unknown distortion, false stars (hot pixels, noise) and a mirrored "
    "detector (the parity is found and reported). The tetra3rs pattern engine proposes matches; frames it cannot "
    "match are tried again with the project's own pair-anchored matcher at the focal length the identified frames "
    "measured (without a measured one, over a scan of focal lengths; a frame it cannot identify stops after a fixed "
    "number of anchor pairs, every pair of its 7 brightest stars at the nominal and of its 3 brightest at each other "
    "scanned focal length, and is reported as 'no match within N anchor pairs'). Every match is then verified "
    "with the project's interstar test, and a frame is accepted only when "
    "enough stars verify; a star that two catalogue stars could be is left unidentified. Then the session is "
    "calibrated and identified again with the calibrated camera, round after round until one adds nothing (--rounds; "
    "each round's additions are printed and reported). Faint candidates (rows with an snr, from hostlink "
    "centroid) build no pattern; after the rounds, one is named only where the camera calibrated on the identified "
    "stars predicts a catalogue star within 99 % of the position uncertainty and as bright as predicted, with no "
    "second catalogue star that could be it (round 'guided': stars searched, added and expected by chance). "
    "Works from under 10 to about 50 deg fields. Writes the "
    "session with the identified star_id (and ra_deg/dec_deg when the file has "
    "those columns, or when a star is an unresolved pair: then the blend's expected centroid for it and every "
    "identified row's catalogue place, its sigma_px grown by that reference's uncertainty); frames that fail keep "
    "star_id 0 and are reported. Exit 2 when no frame is identified. A nominal whose image_size_px is not the size "
    "of the images the session records (image_width_px, image_height_px: hostlink centroid writes them, identify "
    "keeps them) is refused in one line (exit 2), naming a 90-deg turn or a k x k binning when the sizes show one, "
    "as is one that a centroid lies off."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("session", metavar="SESSION.csv", help="session file (docs/file-formats.md)")
    parser.add_argument(
        "--nominal",
        required=True,
        metavar="NOMINAL.json",
        help="nominal camera parameter file (focal length within 10 %%; a path or builtin:NAME)",
    )
    parser.add_argument("--out", required=True, metavar="SESSION.csv", help="session file to write (may be the input)")
    parser.add_argument(
        "--maglim", type=float, metavar="MAG", help="use only catalogue stars at least this bright (Hp; default all)"
    )
    parser.add_argument(
        "--rounds",
        type=int,
        default=None,
        metavar="N",
        help="identify, calibrate, identify again with the calibrated camera, until a round adds nothing, at most N "
        "rounds (default 4; 1: identify once with the nominal)",
    )
    parser.add_argument("--report", metavar="REPORT.json", help="write the per-frame report (attitude, parity, scale)")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_json_argument(parser, "the per-frame report (REPORT.json's object)")


def run(args: argparse.Namespace) -> int:
    import math
    from pathlib import Path

    from hostlink.api import (
        MAX_ROUNDS,
        UserError,
        check_on_detector,
        identify_iteratively,
        load_params,
        progress_bar,
        read_session,
        write_json,
        write_session,
    )

    session = read_session(args.session)
    nominal = load_params(args.nominal)
    check_on_detector(session, nominal.image_size_px, Path(args.session).name, args.nominal)
    if args.maglim is not None and not math.isfinite(args.maglim):
        raise UserError(f"--maglim must be a finite magnitude, got {args.maglim}")
    rounds = MAX_ROUNDS if args.rounds is None else args.rounds
    if rounds < 1:
        raise UserError(f"--rounds must be at least 1, got {rounds}")
    # the bar starts again with each round (each goes over the frames again, with the camera calibrated before)
    with progress_bar("identifying frames", session.n_frames, enabled=not (args.quiet or args.json)) as advance:
        result = identify_iteratively(
            session, nominal, maglim=args.maglim, max_rounds=rounds, progress=lambda done, _total: advance(done)
        )
    if not result.frames:
        raise UserError(f"{args.session}: no unidentified star (every star_id is already set)")
    if args.report:
        write_json(args.report, result.report())
    if args.json:
        from hostlink.commands.jsonopt import print_json

        print_json(result.report())
        args.quiet = True  # the object alone on stdout
    if result.n_frames_identified == 0:
        raise UserError(
            f"no frame identified ({len(result.frames)} tried, engine {result.engine}): check the nominal focal "
            "length (within 10 %), the image size and that the centroids are stars"
        )
    write_session(args.out, result.session)
    if not args.quiet:
        for f in result.frames:
            if f.status == "identified":
                parity = "mirrored" if f.mirrored else "normal"
                print(
                    f"frame {f.frame}: {f.n_identified} of {f.n_centroids} identified ({f.n_candidates} candidates), "
                    f"boresight ra {f.ra_deg:.4f} dec {f.dec_deg:.4f} roll {f.roll_deg:.2f} deg, parity {parity}, "
                    f"scale {f.scale:.4f}, residual {f.residual_arcsec:.1f} arcsec"
                )
            else:
                print(f"frame {f.frame}: not identified ({f.status}; {f.n_centroids} centroids)")
        for r in result.rounds:
            verdict = "" if r["kept"] else " (nothing new: the round before stands)"
            print(
                f"round {r['round']} ({r['camera']}, f {r['focal_length_px']:.2f} px): {r['stars_identified']} stars "
                f"in {r['frames_identified']} frames, {r['added']} added, {r['lost']} lost, {r['renamed']} renamed"
                f"{verdict}"
            )
        parity = "mirrored (flip x before calibrate)" if result.mirrored else "normal"
        camera = result.camera or nominal  # the last round's camera: its scale is relative to it
        focal_ratio = result.scale * camera.focal_length_px / nominal.focal_length_px
        guided = [r for r in result.rounds if r["round"] == "guided" and "expected_false" in r]
        if guided:
            print(
                f"faint candidates admitted: {guided[0]['added']} of the {guided[0]['searched']} catalogue stars "
                f"searched (by chance, noise would put {guided[0]['expected_false']:.1f} there); "
                f"{guided[0]['frames_declined']} frame(s) admitted none, chance explaining over "
                f"{100 * guided[0]['max_false_fraction']:.0f} % of their admissions"
            )
        print(
            f"identified {result.n_identified} stars"
            + (f" and admitted {guided[0]['added']} more at predicted places" if guided else "")
            + f" in {result.n_frames_identified} of {len(result.frames)} frames "
            f"({result.engine}); parity {parity}; focal length {focal_ratio:.4f} x nominal; wrote {args.out}"
        )
    return 0
