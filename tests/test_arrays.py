"""models.arrays.check_array: each way an array can be wrong is refused with the field's name,
as the caller's error class; Mesh validates its fields through it."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.models.arrays import check_array
from facewire.models.mesh import Mesh, MeshError


class _Refused(ValueError):
    pass


@pytest.mark.parametrize("value, message", [
    ([[0.0, 0.0, 0.0]], r"^points: expected a numpy array, got list$"),
    (np.zeros((2, 3), np.float64), r"^points: expected dtype float32, got float64$"),
    (np.zeros((2, 2), np.float32), r"^points: expected shape \(\*, 3\), got \(2, 2\)$"),
    (np.zeros(3, np.float32), r"^points: expected shape \(\*, 3\), got \(3,\)$"),
    (np.array([[0.0, np.nan, 0.0]], np.float32), r"^points: contains NaN or infinity$"),
])
def test_a_wrong_array_is_refused_with_its_name(value, message) -> None:
    with pytest.raises(_Refused, match=message):
        check_array("points", value, np.float32, (None, 3), _Refused)


def test_a_right_array_gives_its_first_dimension() -> None:
    assert check_array("points", np.zeros((7, 3), np.float32), np.float32, (None, 3), _Refused) == 7
    assert check_array("ids", np.zeros(4, np.int32), np.int32, (4,), _Refused) == 4


def test_a_mesh_refuses_a_field_of_the_wrong_size() -> None:
    tri = np.array([[0, 1, 2]], np.int32)
    with pytest.raises(MeshError, match=r"^uv: expected shape \(3, 2\), got \(2, 2\)$"):
        Mesh(vertices=np.zeros((3, 3), np.float32), triangles=tri, uv=np.zeros((2, 2), np.float32),
             tags=np.zeros(1, np.uint8), landmarks=np.zeros(68, np.int32),
             phantoms=np.zeros(13, np.int32))
