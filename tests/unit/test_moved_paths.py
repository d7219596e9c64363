"""Old module paths (before the pipeline layout) import for one release, warn, and are the new
modules themselves."""

import importlib
import sys

import pytest

from tetdose._moved import MOVED


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_path_is_the_new_module_with_a_warning(old):
    sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning, match=MOVED[old].replace(".", r"\.")):
        module = importlib.import_module(old)
    assert module is importlib.import_module(MOVED[old])


def test_old_from_import_still_gives_the_same_class():
    sys.modules.pop("tetdose.mesh", None)
    with pytest.warns(DeprecationWarning):
        from tetdose.mesh import TetMesh
    from tetdose.core.mesh import TetMesh as New
    assert TetMesh is New
