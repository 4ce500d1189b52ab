"""A batched torch engine of the whole closed loop: E scenes at once, on the CPU or a CUDA device.

The same simulator as :mod:`vitfly.sim` with the native physics back end (scenes converted from the
same generators, camera, airframe and integrator, cascaded controller, privileged expert, contact,
goal, bounds and timeouts), as tensor code: one file per part, the episode loop in ``rollout.py``.
In float64 on the CPU it reproduces the numpy engine to rounding (docs/simulator.md, "Batched
engine"); the camera and the dynamics are differentiable, and ``differentiable.py`` flies the whole loop
(camera, policy, controller, physics) for a fixed number of ticks keeping the autograd graph.
"""
