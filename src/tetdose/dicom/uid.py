"""Deterministic DICOM UIDs: the same content and parameters always give the same UIDs.

A UID is ``pydicom.uid.generate_uid(prefix, entropy_srcs=[...])``: the SHA-512 of the entropy
strings, truncated to fit the 64-character limit (PS3.5 §9). With ``prefix=None`` the UID is
``2.25.<integer>`` with the first 128 bits of the SHA-256 of the same strings (PS3.5 §B.2, a
UUID-style UID needing no registered root; pydicom would ignore the entropy there).
Reruns with identical inputs therefore write byte-identical files, while any change of voxel
values, geometry or series parameters yields new UIDs, as PS3.3 requires for new content.
"""

from __future__ import annotations

import hashlib

import numpy as np
from pydicom.uid import UID, generate_uid

from tetdose.core.image import Image

#: Default root: pydicom's registered prefix, under which derived UIDs are unique.
DEFAULT_PREFIX = "1.2.826.0.1.3680043.8.498."


def derive_uid(*parts: object, prefix: str | None = DEFAULT_PREFIX) -> UID:
    """UID determined by ``parts`` (stringified, in order) under ``prefix`` (``None``: 2.25.)."""
    entropy = ["\x1f".join(["tetdose", *(str(p) for p in parts)])]  # separated: no ambiguity
    if prefix is None:
        digest = hashlib.sha256(entropy[0].encode()).digest()
        return UID(f"2.25.{int.from_bytes(digest[:16], 'big')}")
    if not prefix.endswith("."):
        prefix = prefix + "."
    return generate_uid(prefix=prefix, entropy_srcs=entropy)


def image_digest(image: Image, *extra: object) -> str:
    """BLAKE2b hex digest of the voxel values (in their dtype), the grid and ``extra``."""
    h = hashlib.blake2b(digest_size=32)
    values = np.ascontiguousarray(image.array)
    h.update(values.dtype.str.encode())
    h.update(memoryview(values).cast("B"))
    grid = image.grid
    for a in (grid.origin_mm, grid.spacing_mm, grid.direction, np.asarray(grid.size, float)):
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    h.update(repr(extra).encode())
    return h.hexdigest()
