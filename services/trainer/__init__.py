"""Trainer service: MuJoCo models uploaded over HTTP become emulators in the artifact registry (``app``,
``worker``); ``neuro train`` (``neuroanimator.cli``) does the same on the command line."""
