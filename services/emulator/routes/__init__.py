"""HTTP routes of the emulator service."""
