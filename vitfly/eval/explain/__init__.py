"""What the networks look at, over a flight: attention and Grad-CAM maps, and numbers for them.

Python API (``vitfly explain`` is a thin wrapper)::

    from vitfly.eval.explain import fly_trial, load_policies, explain_trial
    from vitfly.sim import ExpertPolicy, make_scene
    frames = fly_trial(make_scene("spheres", "medium", 3), 5.0, ExpertPolicy(), "expert")
    result = explain_trial(load_policies(["runs/vit_lstm/best.ckpt", "random:convnet"]), frames, "runs/explain")
    result.rows()        # per (model, map): temporal consistency, edge mass share, edge lift

- ``frames``: the trial every model is shown (flown: ``fly_trial``; recorded: ``frames_from_arrays``),
  with the obstacle edge masks (``edges``);
- ``maps``: one documented method per map kind (``explain_sequence``; Grad-CAM by captum, attention
  through forward hooks on the mix-transformer's attention layers);
- ``map_metrics``: temporal consistency and the share of map mass on obstacle edges;
- ``figures``: PNG strips and GIFs; ``run``: all of it for several models (``explain_trial``);
- ``policies``: what ``--policy`` names.
"""

from vitfly.eval.explain.edges import EdgeConfig, depth_edge_masks, obstacle_edge_mask, scene_edge_masks
from vitfly.eval.explain.frames import TrialFrames, fly_trial, frames_from_arrays, scene_from_dataset_config
from vitfly.eval.explain.map_metrics import edge_mass_share, map_metrics, temporal_consistency
from vitfly.eval.explain.maps import METHODS, SequenceMaps, explain_sequence, received_attention_map
from vitfly.eval.explain.policies import ExplainedPolicy, load_policies, load_policy
from vitfly.eval.explain.run import ExplainResult, explain_trial

__all__ = [
    "EdgeConfig",
    "ExplainResult",
    "ExplainedPolicy",
    "METHODS",
    "SequenceMaps",
    "TrialFrames",
    "depth_edge_masks",
    "edge_mass_share",
    "explain_sequence",
    "explain_trial",
    "fly_trial",
    "frames_from_arrays",
    "load_policies",
    "load_policy",
    "map_metrics",
    "obstacle_edge_mask",
    "received_attention_map",
    "scene_edge_masks",
    "scene_from_dataset_config",
    "temporal_consistency",
]
