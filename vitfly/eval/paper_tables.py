"""Numbers quoted from the paper (ViTfly, Bhattacharya et al. 2024), for tables that put ours beside them.

Ablation against state information (paper's ``tables/table-no-state-info``): success rates (%)
per environment, model and speed (m/s), without and with the state input (desired speed and
attitude quaternion). Keys are vitfly registry names.
"""

from __future__ import annotations

ABLATION_SPEEDS = (3.0, 5.0, 7.0)
ABLATION_ENVS = ("spheres", "trees")

# env -> model -> ((no state, with state) at 3 m/s, at 5 m/s, at 7 m/s), success %
PAPER_NO_STATE_SUCCESS: dict[str, dict[str, tuple[tuple[int, int], ...]]] = {
    "spheres": {
        "convnet": ((27, 63), (18, 54), (10, 36)),
        "lstmnet": ((27, 45), (18, 9), (9, 9)),
        "unet_lstm": ((36, 27), (18, 9), (27, 9)),
        "vit": ((81, 54), (18, 27), (18, 18)),
        "vit_lstm": ((54, 72), (45, 45), (9, 36)),
    },
    "trees": {
        "convnet": ((90, 100), (81, 63), (60, 42)),
        "lstmnet": ((90, 90), (40, 63), (36, 63)),
        "unet_lstm": ((100, 72), (60, 63), (45, 54)),
        "vit": ((90, 100), (81, 81), (81, 80)),
        "vit_lstm": ((90, 100), (81, 80), (50, 70)),
    },
}

MODEL_LABELS = {
    "convnet": "ConvNet",
    "lstmnet": "LSTMnet",
    "unet_lstm": "UNet+LSTM",
    "vit": "ViT",
    "vit_lstm": "ViT+LSTM",
    "resnet18": "ResNet-18",
}


def paper_success(env: str, model: str, speed: float, use_state: bool) -> int | None:
    """The paper's success rate (%) for this cell, or None where the paper has no number."""
    table = PAPER_NO_STATE_SUCCESS.get(env, {}).get(model)
    if table is None or float(speed) not in ABLATION_SPEEDS:
        return None
    return table[ABLATION_SPEEDS.index(float(speed))][int(bool(use_state))]
