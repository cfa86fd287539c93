"""Simulated worlds with exact ground truth (issue 3): scenarios, renderer, camera effects.

    from semloc_core.sim import make_scenario
    sc = make_scenario("tabletop", seed=0, frames=300)
    image = sc.image(0)                 # BGR uint8, rendered on demand
    sc.T_world_cam, sc.poses2d, sc.odometry, sc.semantic_map, sc.loop_gt, sc.visible_objects(0)

See docs/sim.md.
"""

from semloc_core.sim.effects import Realism
from semloc_core.sim.renderer import Lighting, Renderer, RenderOutput
from semloc_core.sim.scenario import ExemplarSettings, LoopSettings, OdometryNoise, Scenario
from semloc_core.sim.scenarios import SCENARIOS, aliased, hall, make_scenario, route, tabletop
from semloc_core.sim.world import World, WorldBuilder

__all__ = [
    "SCENARIOS",
    "ExemplarSettings",
    "Lighting",
    "LoopSettings",
    "OdometryNoise",
    "Realism",
    "RenderOutput",
    "Renderer",
    "Scenario",
    "World",
    "WorldBuilder",
    "aliased",
    "hall",
    "make_scenario",
    "route",
    "tabletop",
]
