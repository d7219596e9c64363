"""``tetdose voxelize``: virtual CT from a mapped mesh, on the grid of a reference image."""

from __future__ import annotations

import argparse

import numpy as np

from tetdose.cli._common import (
    add_calibration_arg,
    add_output_args,
    calibration_from,
    check_output,
    density_or_word,
    read_mapped_mesh,
)
from tetdose.core.image import Image, check_ct_hu
from tetdose.core.io import IMAGE_SUFFIXES, read_image, write_image
from tetdose.core.voxelize import PARTIAL_MODES, voxelize


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mesh", required=True, help="mapped mesh (point_data 'density' in g/cm³)")
    p.add_argument("--like", required=True, help="image whose grid the output uses (e.g. the CT)")
    add_output_args(p, "output image (.nrrd, .mha, .nii.gz …)", folder=False)
    p.add_argument("--hu", action="store_true", help="write HU (inverse calibration), not g/cm³")
    p.add_argument("--partial", choices=PARTIAL_MODES, default="mass",
                   help="voxels partly inside: plain partial volume (mass) or the paper's "
                        "extrapolation of the inside density")
    p.add_argument("--background", default="air", type=density_or_word(("air", "ct")),
                   help="outside the mesh: air, ct (the --like image through the calibration), "
                        "or a density ≥ 0 in g/cm³")
    add_calibration_arg(p)


def run(args: argparse.Namespace) -> int:
    check_output(args, suffixes=IMAGE_SUFFIXES)
    mesh = read_mapped_mesh(args.mesh)
    like = read_image(args.like)
    cal = calibration_from(args)
    background: str | float | Image = args.background
    if args.background == "ct":
        like = check_ct_hu(like, f"--like {args.like} (used as --background ct)")
        background = like.with_array(cal.density_checked(like.array, f"the CT {args.like}")[0])
    img = voxelize(mesh, mesh.point_data["density"], like.grid, background=background,
                   partial=args.partial, progress=not args.quiet)
    if args.hu:
        img = img.with_array(np.round(cal.hu_of(img.array)).astype(np.int16))
    else:
        img = img.with_array(img.array.astype(np.float32))
    write_image(args.output, img)
    print(f"virtual CT {like.grid.size} ({'HU' if args.hu else 'g/cm³'}) → {args.output}")
    return 0
