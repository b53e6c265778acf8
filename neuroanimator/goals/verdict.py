"""How a controller job ended, in the words a report gives it.

A job's ``status`` (succeeded, failed, cancelled) says whether its run ended normally: a job whose
optimisation ran to its end is ``succeeded`` whether or not its controller does what the task asks.
Read alone, that word claims more than the run showed when the job states no success criterion (a
pendulum still 2.8 rad from its goal "succeeded"), so a report says the verdict instead: whether the
controller meets the criterion on MuJoCo, and that there was none to meet when there is none.
"""

from __future__ import annotations

from typing import Final

SUCCEEDED: Final = "succeeded"
NO_CRITERION: Final = "done, no criterion"
EMULATOR_ONLY: Final = "done, criterion met on the emulator only"
MISSED: Final = "done, criterion missed"


def verdict(
    status: str,
    success_criterion: str | None,
    success_emulator: bool | None,
    success_physics: bool | None,
) -> str:
    """The job's verdict: ``failed`` or ``cancelled`` as its status says; for a run that ended
    normally, ``succeeded`` only when its controller meets the success criterion on MuJoCo (the
    physics is what it is for), and otherwise one of ``done, no criterion``, ``done, criterion met on
    the emulator only``, ``done, criterion missed``."""
    if status != "succeeded":
        return status
    # a job without criterion has no verdict on either side (its criterion's text then says there is
    # none: criteria.describe words an empty one "no success criterion")
    if success_physics is None and success_emulator is None:
        return NO_CRITERION
    if success_physics is True:
        return SUCCEEDED
    if success_emulator is True:
        return EMULATOR_ONLY
    return MISSED
