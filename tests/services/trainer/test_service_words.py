"""A training's refusal comes back in the words of the place the user is: the service's form fields
(and the dashboard's labels), not ``neuro``'s flags."""

from __future__ import annotations

from neuroanimator.training.super_step import ModelOutOfReach, check_useful
from services.trainer.run import in_service_words


def test_the_acceptance_refusal_names_the_form_fields() -> None:
    try:
        check_useful("pend", 50, 0.004, 0.006)
    except ModelOutOfReach as exc:
        text = in_service_words(str(exc))
    else:
        raise AssertionError("an emulator hardly better than linear was kept")
    assert "--" not in text, text
    assert "super_step (Super-step)" in text and "examples (Sample budget)" in text
    assert (
        "force=true keeps it anyway" in text
        and "keep the emulator even if it misses the accuracy bar" in text
    )
