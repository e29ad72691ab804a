"""Planning-grid construction from a sparse 3-D map."""
import numpy as np
import pytest

from coop_viewplan.grid import MapError, planning_bounds


def test_planning_bounds_stop_padding_at_the_ceiling():
    keys = np.array([[0, 0, -1], [10, 5, 3]])         # a map from -0.1 m to 0.3 m at 0.1 m
    lo, hi = planning_bounds(keys, 0.1, pad_m=0.5)
    assert lo.tolist() == [-5, -5, -6] and hi.tolist() == [15, 10, 8]
    # ceiling 1.0 m: no padding above; the top is the ceiling's voxel (10)
    lo, hi = planning_bounds(keys, 0.1, pad_m=0.5, ceiling_m=1.0)
    assert lo.tolist() == [-5, -5, -6] and hi.tolist() == [15, 10, 10]
    # a map reaching above the ceiling keeps its own top; the cameras are always inside
    tall = np.vstack([keys, [[3, 3, 25]]])
    assert planning_bounds(tall, 0.1, pad_m=0.5, ceiling_m=1.0)[1][2] == 25
    assert planning_bounds(keys, 0.1, pad_m=0.5, ceiling_m=0.2, camera_height_m=0.8)[1][2] == 9
    with pytest.raises(MapError, match='keys'):
        planning_bounds(np.zeros((0, 3)), 0.1, pad_m=0.5)
