"""Trainer service: turns MuJoCo models into exported emulators (see ``neuroanimator.cli``)."""
