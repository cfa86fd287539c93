import numpy as np
import pytest

from semloc_core.mapping import VoxelGrid


def test_thesis_volume_shape():
    grid = VoxelGrid.from_bounds([-1, -1, 0], [1, 1, 0.7], 0.01)
    assert grid.shape == (200, 200, 70)
    assert grid.volume_shape == (70, 200, 200)
    np.testing.assert_allclose(grid.bounds, [[-1, -1, 0], [1, 1, 0.7]], atol=1e-12)


def test_centres_and_indices_round_trip():
    grid = VoxelGrid.from_bounds([0.5, -0.3, 0.1], [1.2, 0.4, 0.5], 0.05)
    rng = np.random.default_rng(0)
    idx = np.stack([rng.integers(0, n, 50) for n in grid.shape], axis=1)
    back, inside = grid.indices_of(grid.centres(idx))
    assert inside.all()
    np.testing.assert_array_equal(back, idx)
    np.testing.assert_allclose(grid.axis_centres(2), 0.125 + 0.05 * np.arange(grid.nz))
    _, inside = grid.indices_of([[0.49, 0.0, 0.2], [0.6, 0.0, 0.6]])
    assert not inside.any()


def test_document_round_trip():
    grid = VoxelGrid.from_bounds([0, 0, 0], [1, 2, 0.3], 0.1)
    again = VoxelGrid.from_document(grid.to_document())
    assert again.shape == grid.shape and again.voxel_size == grid.voxel_size
    np.testing.assert_array_equal(again.origin, grid.origin)


@pytest.mark.parametrize(
    "lo, hi, size, message",
    [
        ([0, 0, 0], [1, 1, 0], 0.1, "below max"),
        ([0, 0, 0], [1, 1, 1], 0.0, "positive"),
        ([0, 0, np.nan], [1, 1, 1], 0.1, "finite"),
        ([0, 0], [1, 1], 0.1, "3-vectors"),
    ],
)
def test_bad_bounds(lo, hi, size, message):
    with pytest.raises(ValueError, match=message):
        VoxelGrid.from_bounds(lo, hi, size)


def test_a_grid_reads_in_millimetres_in_progress_lines():
    """semloc eval mapping's "mapping N frames ... into {grid}" printed every float digit of the corners."""
    grid = VoxelGrid(np.array([-0.8932224308550131, -0.7194649439455346, 0.73]), 0.01, (179, 144, 70))
    assert str(grid) == "179 x 144 x 70 voxels of 1 cm from (-0.893, -0.719, 0.730) to (0.897, 0.721, 1.430) m"
    assert "0.8932224308550131" in repr(grid)
