"""Sensor models that turn an exact depth render into what a real depth camera delivers (numpy only).

The lowest layer with ``zoo`` and ``datamodules``: it imports nothing else of vitfly, so the simulator
(``vitfly.sim.rollout``: modelled frames in flight) and the datamodule (``vitfly.datamodules.sensor_augment``:
modelled frames as domain randomisation in training) share one model.
"""
