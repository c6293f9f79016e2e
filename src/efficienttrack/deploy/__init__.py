"""Deployment: the rollout, the runtime guard, the torch and ONNX runtimes, export, the fixed-rate loop."""
