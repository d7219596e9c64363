"""
tetdose as the coupling layer: phases out to another code, doses back in
========================================================================

The job: keep the transport code you trust (Geant4, TOPAS, PHITS, MCNP6, EGSnrc) and let
tetdose do the breathing anatomy: export each phase in a format that code reads, run it, and
bring its per-phase doses back onto the mesh, where they are accumulated over the phases on the
same matter. Here ``ompmc`` (a C port of EGSnrc's coupled photon–electron transport on voxels,
the extra ``tetdose[ompmc]``) stands in for the other code, following the EGSnrc/DOSXYZnrc
recipe of :doc:`/user-guide/coupling`: virtual phase CTs out, a ``.3ddose``-like voxel dose
per phase back in.
"""

# %%
# The breathing phases
# --------------------
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import tetdose

work = Path(tempfile.mkdtemp(prefix="tetdose-ex4-"))


def tetdose_cli(*args: str) -> None:
    """Run ``tetdose ARGS`` in the work folder and show its output (what a terminal shows)."""
    done = subprocess.run([sys.executable, "-m", "tetdose", *args, "-q"], cwd=work,
                          capture_output=True, text=True)
    print(f"$ tetdose {' '.join(args)}\n{done.stdout}{done.stderr}")
    done.check_returncode()


tetdose_cli("phantom", "lung", "--size", "small", "--mesher", "structured", "-o", "lung")
tetdose_cli("map", "--ct", "lung/ct.nrrd", "--mesh", "lung/mesh.vtu", "-o", "mapped.vtu")
tetdose_cli("deform", "--mesh", "mapped.vtu", "--breathing", "--n-phases", "3", "-o", "phases")

# %%
# Phases out, for a code that tracks on tetrahedra
# ------------------------------------------------
# Geant4 (G4Tet), TOPAS and PHITS read TetGen ``.node/.ele`` with a ``.material`` file (the
# ICRP 145 layout); MCNP6 reads Abaqus ``.inp``. Each tet gets its mass-keeping mean density
# and its composition class; densities are binned into as few materials as keep the mass
# within 0.1 %.
tetdose_cli("export-phases", "--phases", "phases", "--format", "tetgen", "-o", "out")
export = json.loads((work / "out/export.json").read_text())
print(json.dumps(export, indent=1, default=str)[:1200])
print(sorted(p.name for p in (work / "out").iterdir())[:8])

# %%
# Phases out, for a voxel code: the virtual 4D-CT
# -----------------------------------------------
# The stand-in here tracks on voxels, as DOSXYZnrc does: each phase goes out as its virtual CT
# (the mesh voxelized mass-exactly, the reference CT outside it).
tetdose_cli("4dct", "--phases", "phases", "--like", "lung/ct.nrrd", "--format", "nrrd",
            "-o", "v4d")
phase_cts = sorted((work / "v4d").glob("phase_*.nrrd"))
print([p.name for p in phase_cts])

# %%
# The other code runs each phase
# ------------------------------
# ``tetdose dose --engine ompmc`` runs ompmc on a CT's voxels with tetdose's own beam sampling
# (handed over as an IAEA phase space) and writes a voxel dose — standing in for DOSXYZnrc's
# ``.3ddose`` or a Geant4 run's per-tet tally. Its warning is expected: ompmc scores nothing in
# voxels below 0.0435 g/cm³ (here the air around the phantom), and says so.
(work / "plan.toml").write_text("""
[[beam]]
type = "parallel"
energy_mev = 2.0
position_mm = [0.0, -150.0, 0.0]
direction = [0.0, 1.0, 0.0]
field_mm = [40.0, 40.0]
""")
(work / "other").mkdir()
for ct in phase_cts:
    tetdose_cli("dose", "--ct", str(ct.relative_to(work)), "--plan", "plan.toml",
                "--engine", "ompmc", "--histories", "2000", "-o", f"other/{ct.stem}.nrrd")

# %%
# Doses back in, accumulated on the mesh
# --------------------------------------
# ``import-dose`` puts each voxel dose onto the tets by energy, E_k = Σ_v D_v ρ_v Vol(v ∩ k),
# with the densities the other code ran on (``--ct``: the phase CTs in HU), then accumulates
# over the phases with their time weights and uncertainties, as ``dose4d`` does.
doses = sorted(str(p.relative_to(work)) for p in (work / "other").glob("phase_*.nrrd")
               if "_std" not in p.name)
tetdose_cli("import-dose", "--phases", "phases", "--dose", *doses,
            "--ct", *(str(p.relative_to(work)) for p in phase_cts), "-o", "dose4d")
acc = tetdose.read_mesh(work / "dose4d/accumulated.vtu")
dose, mass = acc.cell_data["dose"], acc.cell_data["mass_g"]
print(f"{acc.n_tets} tets, total mass {mass.sum():.3f} g, "
      f"mean dose {np.sum(dose * mass) / mass.sum():.3e} (mass-weighted), max {dose.max():.3e} "
      "Gy per source particle")

# %%
# The accumulated mesh dose along the beam
# ----------------------------------------
# ``compare`` and ``export-dose`` take this folder as they take ``dose4d``'s: the imported
# dose goes on with the rest of the workflow unchanged.
c = acc.centroids_mm
near_axis = (abs(c[:, 0]) < 10) & (abs(c[:, 2]) < 10)
fig, ax = plt.subplots(figsize=(7, 4))
ax.plot(c[near_axis, 1], dose[near_axis], ".", ms=4)
ax.set_xlabel("tet centroid y [mm] (beam direction)")
ax.set_ylabel("accumulated dose [Gy per source particle]")
ax.set_title("ompmc doses accumulated on the mesh (tets within 10 mm of the axis)")
fig.tight_layout()

shutil.rmtree(work)
