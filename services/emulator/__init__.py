"""Emulator service: many clients' sessions stepped by exported emulators in batched ONNX Runtime calls.

The process never imports PyTorch: it reads artifacts (manifest, ONNX graph, MJCF) directly.
"""
