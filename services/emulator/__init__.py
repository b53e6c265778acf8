"""Emulator service: many clients' sessions stepped by exported emulators in batched ONNX Runtime calls.

The process never imports PyTorch: it reads artifacts (manifest, ONNX graph, MJCF) directly.

Where things are: ``service.py`` (``EmulatorService``, what one process holds); ``stepping.py`` (the
stepping core every transport goes through), with ``inputs.py`` (the checks of inputs) and
``envelope.py`` (whether new states lie in the training envelope); ``batcher.py`` (one ORT call per
batch); ``sessions.py`` (the session table as arrays); ``registry.py`` (the loaded emulators);
``errors.py`` and ``error_mapping.py`` (typed domain errors, and what a client receives for each). The
transports: ``routes/`` (REST), ``fastpath.py`` (the binary ``POST /step``) and ``ws/`` (websockets).
Beside them: ``persistence.py`` (Redis checkpoints), ``scene.py`` (geometry, poses, the MuJoCo
shadow), ``metrics.py``, ``settings.py`` and ``app.py``.
"""
