"""DICOM export: CT series (3-D and 4D-CT) and RT Dose, written with pydicom.

Files are Explicit VR Little Endian, deterministic (UIDs derived from content, see
:mod:`tetdose.dicom.uid`) and written atomically (a failure leaves no partial output).
"""

from tetdose.dicom.ct_series import write_ct_series, write_ct_series_4d
from tetdose.dicom.rt_dose import rt_plan_path, write_rt_dose

__all__ = ["rt_plan_path", "write_ct_series", "write_ct_series_4d", "write_rt_dose"]
