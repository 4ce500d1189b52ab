"""The simulator's name for the stereo depth sensor models, which live in :mod:`vitfly.sensors.stereo`.

The model is numpy only and needs nothing of the simulator, so it sits below ``sim`` where the datamodule
(training-time domain randomisation) may use it too; this module keeps ``vitfly.sim.sensor_models`` working.
"""

from vitfly.sensors.stereo import (
    PROPELLER_CORNERS,
    PROPELLER_READS,
    SENSOR_MODELS,
    FrameDelay,
    ImageGeometry,
    StereoDepthConfig,
    StereoDepthSensor,
    occlusion_mask,
    propeller_mask,
    sensor_dict,
    sensor_flag_values,
    sensor_from_dict,
)

__all__ = ["FrameDelay", "ImageGeometry", "PROPELLER_CORNERS", "PROPELLER_READS", "SENSOR_MODELS",
           "StereoDepthConfig", "StereoDepthSensor", "occlusion_mask", "propeller_mask", "sensor_dict",
           "sensor_flag_values", "sensor_from_dict"]
