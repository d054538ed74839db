"""``mcam evaluate``: quality metrics of a reconstruction against a reference image."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

from models.errors import InvalidInputError
from models.exr_header import values_scene_referred
from models.hdr_io import read_hdr
from models.winding_files import read_winding
from service.cli.options import add_clip_negative_flag
from service.cli.output_files import check_inputs

#: Display names and units of the metrics in the table.
LABELS: dict[str, tuple[str, str]] = {
    "winding_accuracy": ("winding accuracy", "fraction of pixels"),
    "psnr": ("PSNR (linear)", "dB"),
    "pu21_psnr": ("PU21-PSNR", "dB"),
    "ssim": ("SSIM (Reinhard)", ""),
    "ms_ssim": ("MS-SSIM (Reinhard)", ""),
    "hdr_flip": ("HDR-FLIP", "mean error"),
}


def register(subparsers: Any) -> None:
    """Add the ``evaluate`` command."""
    parser = subparsers.add_parser(
        "evaluate",
        help="compare a reconstruction with a reference HDR image",
        description="Print winding accuracy, PSNR, PU21-PSNR, SSIM, MS-SSIM (and HDR-FLIP "
        "when installed) of an HDR image against a reference of the same scale.",
    )
    parser.add_argument("image", help="the reconstruction: .exr, .hdr or .pic")
    parser.add_argument("--reference", required=True, help="reference HDR image, same scale")
    parser.add_argument("--winding", metavar="W.png", help="decoded W map (mcam reconstruct)")
    parser.add_argument(
        "--winding-reference", metavar="W.png", help="true W map (mcam simulate --ground-truth)"
    )
    add_clip_negative_flag(parser)
    parser.add_argument("--no-flip", action="store_true", help="skip HDR-FLIP (slow)")
    parser.add_argument("--json", action="store_true", help="print JSON (an infinite PSNR is null)")
    parser.set_defaults(func=run)


def format_table(results: dict[str, float]) -> str:
    """The metrics as aligned text rows: name, value, unit."""
    rows = [(*LABELS.get(name, (name, "")), value) for name, value in results.items()]
    width = max(len(label) for label, _, _ in rows)
    return "\n".join(
        f"{label:<{width}}  {value:>10.4f}  {unit}".rstrip() for label, unit, value in rows
    )


def check_same_units(estimate: dict[str, Any], reference: dict[str, Any]) -> None:
    """Refuse a reconstruction in wrap units (its gain unknown) against a scene-referred
    reference, or the other way round: their PSNRs compared two scales."""
    units = values_scene_referred(estimate), values_scene_referred(reference)
    if None in units or units[0] == units[1]:
        return
    gain = reference.get("gain") or estimate.get("gain")
    hint = f" (--gain {gain})" if gain else ""
    raise InvalidInputError(
        "the reconstruction is in "
        + ("scene-referred x / gain" if units[0] else "wrap units (its gain was unknown)")
        + " but the reference is in "
        + ("scene-referred x / gain" if units[1] else "wrap units")
        + f": reconstruct the frame with its gain{hint} so that both are on one scale"
    )


#: What each W map flag gives, for the refusal of one without the other.
WINDING_FLAGS = {
    "--winding": "the decoded W map, as mcam reconstruct --winding-out writes it",
    "--winding-reference": "the true W map, as mcam simulate --ground-truth writes it",
}


def check_winding_pair(args: argparse.Namespace) -> None:
    """Refuse one W map flag without the other, naming the one to add: winding accuracy
    compares the two ("winding accuracy needs both ... winding maps" named no flag)."""
    if bool(args.winding) == bool(args.winding_reference):
        return
    flags = list(WINDING_FLAGS)
    given, missing = flags if args.winding else flags[::-1]
    raise InvalidInputError(
        f"winding accuracy compares two W maps: {given} needs {missing} "
        f"({WINDING_FLAGS[missing]}); give both, or neither for the image metrics alone"
    )


def run(args: argparse.Namespace) -> int:
    """Read both images (and W maps), compute the metrics, print them."""
    # imported here: scipy.ndimage would add ~0.4 s to the start of every mcam command
    from models.metrics import SSIM_WINDOW, evaluate

    check_winding_pair(args)
    given = (args.image, args.reference, args.winding, args.winding_reference)
    check_inputs([path for path in given if path])
    estimate = read_hdr(args.image, clip_negative=args.clip_negative)
    reference = read_hdr(args.reference, clip_negative=args.clip_negative)
    check_same_units(estimate.attributes, reference.attributes)
    winding = read_winding(args.winding) if args.winding else None
    winding_ref = read_winding(args.winding_reference) if args.winding_reference else None
    results = evaluate(
        estimate.pixels, reference.pixels, winding, winding_ref, flip=not args.no_flip
    )
    if "ssim" not in results:
        height, width = estimate.pixels.shape[:2]
        print(
            f"mcam evaluate: note: no SSIM or MS-SSIM: they need images of at least "
            f"{SSIM_WINDOW} x {SSIM_WINDOW} pixels (their window), these are {height} x {width}",
            file=sys.stderr,
        )
    if args.json:
        print(json.dumps({k: v if math.isfinite(v) else None for k, v in results.items()}))
    else:
        print(format_table(results))
    return 0
