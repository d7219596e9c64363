"""
A virtual 4D-CT and an RT Dose for a planning system
====================================================

The job: hand a planning system (or any DICOM viewer) the breathing phases as a 4D-CT, one CT
series per phase, and a dose on the same frame of reference as an RT Dose, and check that the
files are valid DICOM with ``dciodvfy`` (dicom3tools; ``make tools`` installs it where apt is
available — without it the check is skipped with a note).
"""

# %%
# Phantom, mapping and four breathing phases
# ------------------------------------------
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pydicom

import tetdose

work = Path(tempfile.mkdtemp(prefix="tetdose-ex2-"))


def tetdose_cli(*args: str) -> None:
    """Run ``tetdose ARGS`` in the work folder and show its output (what a terminal shows)."""
    done = subprocess.run([sys.executable, "-m", "tetdose", *args, "-q"], cwd=work,
                          capture_output=True, text=True)
    print(f"$ tetdose {' '.join(args)}\n{done.stdout}{done.stderr}")
    done.check_returncode()


tetdose_cli("phantom", "lung", "--size", "small", "--mesher", "structured", "-o", "lung")
tetdose_cli("map", "--ct", "lung/ct.nrrd", "--mesh", "lung/mesh.vtu", "-o", "mapped.vtu")
tetdose_cli("deform", "--mesh", "mapped.vtu", "--breathing", "--n-phases", "4", "-o", "phases")

# %%
# The virtual 4D-CT as DICOM
# --------------------------
# One CT series per phase, with shared Study and Frame of Reference UIDs and the phase in
# ``TemporalPositionIdentifier``; the mesh voxelized mass-exactly, the reference CT outside it.
tetdose_cli("4dct", "--phases", "phases", "--like", "lung/ct.nrrd", "--format", "dicom",
            "-o", "ct4d")
phases = tetdose.read_4dct(work / "ct4d")
for p in phases:
    print(f"{p.percent:5.1f} %  {Path(p.source).name}  {p.image.grid.size}  "
          f"HU {p.image.array.min():.0f}…{p.image.array.max():.0f}")

# %%
# A prescribed dose, exported as RT Dose on the reference phase's series
# ----------------------------------------------------------------------
# With a ``[prescription]`` the dose is in Gy per fraction and the RT Dose says ``GY``; without
# one it would be per source photon and written as ``RELATIVE``.
(work / "plan.toml").write_text("""
[regions]
lung = 2

[prescription]
structure = "lung"
dose_gy = 2.0
metric = "mean"
fractions = 30

[[beam]]
type = "linac"
name = "AP"
spectrum = "6MV"
isocenter_mm = [0.0, 0.0, 0.0]
gantry_deg = 0.0
jaws_mm = [-30.0, 30.0, -30.0, 30.0]
weight = 100.0
""")
reference = next(d for d in sorted((work / "ct4d").iterdir()) if "050" in d.name)  # 50 % series
tetdose_cli("dose", "--mesh", "phases/phase_002.vtu", "--ct", str(reference.relative_to(work)),
            "--labels", "lung/labels.nrrd", "--plan", "plan.toml", "--histories", "20000",
            "-o", "dose/dose.vtu")
tetdose_cli("export-dose", "--dose", "dose/dose.nrrd", "--like", str(reference.relative_to(work)),
            "-o", "rtdose.dcm")

rd = pydicom.dcmread(work / "rtdose.dcm")
ct0 = pydicom.dcmread(sorted(reference.glob("*.dcm"))[0])
print(rd.Modality, rd.DoseUnits, rd.DoseType, rd.DoseSummationType)
print("same frame of reference as the CT:", rd.FrameOfReferenceUID == ct0.FrameOfReferenceUID)

# %%
# Check the files with dciodvfy
# -----------------------------
# ``dciodvfy`` checks each object against the DICOM standard's module definitions; the lines it
# prints as ``Error`` would make a strict planning system reject the file (``Warning`` lines are
# advisory).
if shutil.which("dciodvfy"):
    for f in (work / "rtdose.dcm", sorted(reference.glob("*.dcm"))[0]):
        out = subprocess.run(["dciodvfy", str(f)], capture_output=True, text=True)
        report = (out.stdout + out.stderr).splitlines()
        errors = [ln for ln in report if ln.startswith("Error")]
        print(f"dciodvfy {f.name}: {len(errors)} errors, "
              f"{sum(ln.startswith('Warning') for ln in report)} warnings")
        print("\n".join(errors))
else:
    print("dciodvfy is not installed (dicom3tools; `make tools`): DICOM check skipped")

# %%
# What the planning system will show
# ----------------------------------
# The RT Dose read back with pydicom (Pixel Data × DoseGridScaling) over the reference CT, and
# the difference the breathing makes between the phase at 0 % and the reference.
dose = rd.pixel_array * float(rd.DoseGridScaling)
ref = next(p for p in phases if p.percent == 50.0).image.array
moved = phases[0].image.array
k = ref.shape[0] // 2  # image arrays and DICOM pixel data are both indexed [z, y, x]
fig, axes = plt.subplots(1, 2, figsize=(9, 4))
axes[0].imshow(ref[k], cmap="gray", vmin=-1000, vmax=300)
high = np.percentile(dose[dose > 0], 99)  # a few noisy voxels would set the maximum
axes[0].imshow(np.ma.masked_less(dose[k], 0.1 * high), cmap="jet", alpha=0.5, vmax=high)
axes[0].set_title(f"RT Dose on the reference CT [{rd.DoseUnits}]")
axes[1].imshow((moved - ref)[k], cmap="RdBu_r", vmin=-300, vmax=300)
axes[1].set_title("phase 0 % − reference [HU]")
for a in axes:
    a.set_axis_off()
fig.tight_layout()

shutil.rmtree(work)
