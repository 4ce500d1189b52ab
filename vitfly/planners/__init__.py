"""The paper's modular baselines: depth -> world points -> local map -> plan -> velocity command.

One file per stage: ``perception`` (back-projection with the simulator camera's own rays), ``mapping``
(a fused local point map with a distance query), ``search`` (FastPlanner-like kinodynamic search with
B-spline smoothing), ``convex`` (a convex free-space region carved from the map, the command from a linear
programme over it), ``policy`` (replanning at a fixed rate with the planning latency applied in simulated
time, tracking the plan at the control rate). ``vitfly evaluate --policy modular:NAME`` flies them.
"""

from vitfly.planners.policy import PLANNER_NAMES, ModularPolicy, PlannerOptions, load_planner_options

__all__ = ["PLANNER_NAMES", "ModularPolicy", "PlannerOptions", "load_planner_options"]
