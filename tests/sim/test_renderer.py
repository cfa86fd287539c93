"""The numba renderer against the independent numpy reference, for every camera model."""

import numpy as np
import pytest

from semloc_core.camera import EquirectangularCamera, PinholeCamera, forward_extrinsic
from semloc_core.sim.reference import render_reference
from semloc_core.sim.renderer import Renderer

CAMERAS = {
    "pinhole": PinholeCamera.from_fov(160, 120, 70.0),
    "distorted": PinholeCamera(160, 120, np.array([[110.0, 0, 80], [0, 110, 60], [0, 0, 1]]),
                               dist=[-0.25, 0.07, 0.001, -0.001, 0.0]),
    "panorama": EquirectangularCamera(256, 64, forward_extrinsic(0.0)),
}


@pytest.mark.parametrize("camera_name", sorted(CAMERAS))
@pytest.mark.parametrize("scenario", ["tabletop", "hall"])
def test_kernel_agrees_with_the_numpy_reference(scenario, camera_name, sim_scenario):
    sc = sim_scenario(scenario, frames=12, seed=2, realism=False)
    camera = CAMERAS[camera_name]
    renderer = Renderer(sc.world)
    for i in (0, 7):
        T = sc.T_world_cam[i] if sc.T_body_cam is not None else sc.T_world_body[i] @ forward_extrinsic(1.5)
        fast = renderer.render(camera, T)
        slow = render_reference(sc.world, camera, T)
        same = fast.ids == slow.ids
        # Only pixels on an outline (a ray grazing an edge) may differ between the two implementations.
        assert same.mean() > 0.995
        finite = np.isfinite(slow.depth) & same
        np.testing.assert_allclose(fast.depth[finite], slow.depth[finite], rtol=1e-4, atol=1e-4)
        assert np.array_equal(np.isfinite(fast.depth), np.isfinite(slow.depth)) or \
            np.mean(np.isfinite(fast.depth) != np.isfinite(slow.depth)) < 0.002


def test_parallel_kernel_gives_the_same_bytes(sim_scenario):
    sc = sim_scenario("tabletop", frames=12, seed=2, realism=False)
    camera = sc.camera
    a = Renderer(sc.world).render(camera, sc.T_world_cam[3])
    b = Renderer(sc.world, parallel=True).render(camera, sc.T_world_cam[3])
    assert np.array_equal(a.colour, b.colour) and np.array_equal(a.depth, b.depth) and np.array_equal(a.ids, b.ids)


def test_render_rejects_bad_input(sim_scenario):
    sc = sim_scenario("tabletop", frames=12, seed=2, realism=False)
    renderer = Renderer(sc.world)
    with pytest.raises(ValueError, match="4x4"):
        renderer.render(sc.camera, np.eye(3))
    with pytest.raises(ValueError, match="finite"):
        renderer.render(sc.camera, np.full((4, 4), np.nan))
    with pytest.raises(TypeError, match="one camera model"):
        renderer.render(object(), np.eye(4))
