"""Deployment: inference-only network rewrites, ONNX export and the ONNX Runtime policy runner."""
