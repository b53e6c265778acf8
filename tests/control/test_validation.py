"""Job specs: ``validate_job`` fills defaults into a ``JobSpec``, names the bad field with the
expected and the got, validates its own output to the same spec, and never imports torch or MuJoCo;
the thesis tasks are plain data defined beside their physical models."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from neuroanimator import catalog
from neuroanimator.catalog.tasks import TASKS
from neuroanimator.contracts.controller import JobCreate, OptimizerSpec
from neuroanimator.control.job import run_job
from neuroanimator.control.validation import validate_job
from neuroanimator.goals.errors import JobSpecError
from neuroanimator.goals.spec import JobSpec
from neuroanimator.goals.terms import ForwardDistanceTerm, StayWithinBoundsTerm

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = ROOT / "artifacts"


def error_of(spec: dict[str, Any]) -> JobSpecError:
    with pytest.raises(JobSpecError) as info:
        validate_job(spec, ARTIFACTS)
    assert isinstance(info.value, ValueError)
    return info.value


def test_task_defaults_are_filled_in() -> None:
    spec = validate_job({"task": "pendulum-swing"}, ARTIFACTS)
    task = TASKS["pendulum-swing"]
    assert isinstance(spec, JobSpec)
    assert spec.model == "pendulum-active"
    assert spec.substeps == 50 and spec.horizon == 40 and spec.points_per_step == 0.5
    assert spec.version == (ARTIFACTS / "pendulum-active" / "latest-n50").read_text().strip()
    assert spec.initial_state == list(task.initial_state)
    assert spec.optimizer.learning_rate == 2.0 and spec.optimizer.momentum == 0.5
    assert spec.success == list(task.success)


def test_the_api_body_validates_like_its_json() -> None:
    body = JobCreate(task="truck-parking", horizon=12, optimizer=OptimizerSpec(max_iterations=5))
    assert validate_job(body, ARTIFACTS) == validate_job(body.spec(), ARTIFACTS)


def test_overrides_and_a_model_only_job() -> None:
    spec = validate_job(
        {"task": "truck-parking", "target_state": [5, 5, 0, 0, 0, 0], "optimizer": {"max_iterations": 7}},
        ARTIFACTS,
    )
    assert spec.target_state == [5.0, 5.0, 0.0, 0.0, 0.0, 0.0]
    assert spec.optimizer.max_iterations == 7 and spec.optimizer.learning_rate == 1.5
    custom = validate_job({"model": "lander", "terms": [{"term": "forward_distance"}], "mu_s": 0}, ARTIFACTS)
    assert custom.task is None and custom.horizon == 40 and custom.points_per_step == 1.0
    assert custom.initial_state[3] == 1.0  # identity quaternion by default
    assert custom.terms == [
        ForwardDistanceTerm(
            term="forward_distance", weight=1.0, direction=[1.0, 0.0, 0.0], variables=[0, 1, 2]
        )
    ]
    assert custom.model_dump()["terms"] == [
        {"term": "forward_distance", "weight": 1.0, "direction": [1.0, 0.0, 0.0], "variables": [0, 1, 2]}
    ]
    assert custom.success == []


# Custom jobs whose spec must survive a second validation: a worker validates the queued JSON again.
CUSTOM_JOBS: list[dict[str, Any]] = [
    {"model": "lander", "terms": [{"term": "forward_distance"}], "mu_s": 0},
    {"model": "lander", "terms": [{"term": "forward_distance", "direction": [1, 1, 0]}], "mu_s": 0},
    {
        "task": "truck-parking",
        "terms": [{"term": "forward_distance", "variables": ["velocity.x", "velocity.y"]}],
    },
    {
        "task": "lander-landing",
        "terms": [{"term": "stay_within_bounds", "variable": "position.z", "low": 0.5}],
    },
    {"task": "lander-landing", "terms": [{"term": "stay_within_bounds", "variable": 2, "high": 30}]},
    {"task": "lander-landing", "initial_state": [0.0] * 3 + [2.0, 1.0, 0.5, 0.25] + [0.0] * 6},
    {
        "task": "truck-parking",
        "terms": [
            {"term": "final_velocity", "variables": ["velocity.x"]},
            {"term": "path_target", "waypoints": [{"time": 5.0, "target": [10, 0, 0, 0, 0, 0]}]},
            {"term": "control_smoothness", "weight": 0.5},
        ],
        "success": [{"check": "range", "variables": ["position.x"], "min": 19}],
    },
    {"model": "pendulum-active", "target_state": [0.5, 0, 0, 0, 0, 0], "optimizer": {"line_search": False}},
    {
        "task": "lander-landing",
        "terms": [{"term": "success_margin", "weight": 10}],
        "optimizer": {"starts": 8, "global_generations": 0},
    },
    {"model": "truck", "terms": [{"term": "success_margin", "margin": 0.3}], "success": []},
]


@pytest.mark.parametrize("job", [{"task": name} for name in sorted(TASKS)] + CUSTOM_JOBS, ids=str)
def test_validation_is_idempotent(job: dict[str, Any]) -> None:
    """A validated spec, as an object or as the JSON a worker reads from the queue, validates to itself."""
    spec = validate_job(job, ARTIFACTS)
    assert validate_job(spec, ARTIFACTS) == spec
    queued = json.loads(spec.model_dump_json())
    assert validate_job(queued, ARTIFACTS) == spec
    assert JobSpec.model_validate(queued) == spec


def test_stay_within_bounds_with_one_bound_and_forward_distance_run_in_the_worker() -> None:
    """Both were accepted on submission and then refused by the worker's second validation."""
    job = {
        "model": "lander",
        "horizon": 2,
        "terms": [
            {"term": "forward_distance"},
            {"term": "stay_within_bounds", "variable": "position.z", "low": 0.5},
        ],
        "optimizer": {"max_iterations": 1, "physics_rounds": 0},
    }
    spec = validate_job(job, ARTIFACTS)
    bounds = spec.terms[1]
    assert isinstance(bounds, StayWithinBoundsTerm) and bounds.low == 0.5 and bounds.high is None
    result = run_job(json.loads(spec.model_dump_json()), ARTIFACTS)
    assert result.status == "succeeded", result.reason
    assert result.spec == spec


def test_quaternions_are_normalised() -> None:
    s = [0.0] * 3 + [2.0, 0.0, 0.0, 0.0] + [0.0] * 6
    assert validate_job({"model": "lander", "initial_state": s}, ARTIFACTS).initial_state[3] == 1.0
    assert "quaternion orientation" in str(error_of({"model": "lander", "initial_state": [0.0] * 13}))


@pytest.mark.parametrize(
    ("spec", "field", "text"),
    [
        (
            {"task": "fly-to-mars"},
            "task",
            "unknown task 'fly-to-mars'; known tasks are ['dolphin-swim', 'lander-landing', ",
        ),
        ({}, "task", "expected a task or a model, got neither"),
        (
            {"model": "submarine"},
            "model",
            "unknown model 'submarine'; trained models are ['ball', 'dolphin', 'lander', ",
        ),
        (
            {"task": "pendulum-swing", "model": "truck"},
            "model",
            "task 'pendulum-swing' runs on model 'pendulum-active', got 'truck'",
        ),
        (
            {"task": "truck-parking", "version": "n0-nope"},
            "version",
            "model 'truck' has no version 'n0-nope'",
        ),
        (
            {"task": "truck-parking", "substeps": 7},
            "substeps",
            "model 'truck' has no emulator for substeps=7; it has [25, 50, 100]",
        ),
        (
            {"task": "truck-parking", "target_state": [1, 2, 3]},
            "target_state",
            "expected 6 state values for model truck, got 3",
        ),
        (
            {"task": "truck-parking", "initial_state": [0, 0, math.nan, 0, 0, 0]},
            "initial_state[2]",
            "expected 6 finite state values for model truck, got nan at index 2",
        ),
        (
            {"task": "truck-parking", "initial_state": [0, 0, math.inf, 0, 0, 0]},
            "initial_state[2]",
            "got inf at index 2",
        ),
        (
            {"task": "truck-parking", "target_state": "home"},
            "target_state",
            "expected a list of 6 state values for model truck, got str",
        ),
        (
            {"task": "truck-parking", "state_weights": [1, 1, 1, 1, 1, -1]},
            "state_weights[5]",
            "expected 6 weights >= 0",
        ),
        ({"task": "truck-parking", "horizon": 0}, "horizon", "expected an integer in [1, 1000], got 0"),
        ({"task": "truck-parking", "horizon": 1001}, "horizon", "expected an integer in [1, 1000], got 1001"),
        ({"task": "truck-parking", "horizon": 2.5}, "horizon", "expected an integer in [1, 1000], got 2.5"),
        (
            {"task": "truck-parking", "optimizer": {"max_iterations": 0}},
            "optimizer.max_iterations",
            "expected an integer in [1, 10000], got 0",
        ),
        (
            {"task": "truck-parking", "optimizer": {"max_iterations": 10001}},
            "optimizer.max_iterations",
            "expected an integer in [1, 10000], got 10001",
        ),
        (
            {"task": "truck-parking", "optimizer": {"learning_rate": 0}},
            "optimizer.learning_rate",
            "expected a number in (0, 100], got 0",
        ),
        (
            {"task": "truck-parking", "optimizer": {"learning_rate": 101}},
            "optimizer.learning_rate",
            "expected a number in (0, 100], got 101",
        ),
        (
            {"task": "truck-parking", "optimizer": {"momentum": 1.0}},
            "optimizer.momentum",
            "expected a number in [0, 1), got 1.0",
        ),
        (
            {"task": "truck-parking", "optimizer": {"momentum": -0.1}},
            "optimizer.momentum",
            "expected a number in [0, 1), got -0.1",
        ),
        (
            {"task": "truck-parking", "optimizer": {"speed": 3}},
            "optimizer.speed",
            "unknown key; the optimizer takes",
        ),
        (
            {"task": "truck-parking", "terms": [{"term": "fly"}]},
            "terms[0].term",
            "unknown term 'fly'; known terms are ['control_effort', ",
        ),
        (
            {"task": "truck-parking", "terms": [{"term": "final_velocity", "variables": ["speed"]}]},
            "terms[0].variables[0]",
            "expected a state label (one of ['position.x', ",
        ),
        (
            {"task": "truck-parking", "terms": [{"term": "stay_within_bounds", "variable": "heading"}]},
            "terms[0]",
            "expected low and/or high bounds, got neither",
        ),
        (
            {"task": "truck-parking", "terms": [{"term": "final_state", "colour": 1}]},
            "terms[0]",
            "unknown parameters ['colour'] for term 'final_state'",
        ),
        (
            {"task": "truck-parking", "terms": [{"term": "control_effort", "weight": -1}]},
            "terms[0].weight",
            "expected a number >= 0.0, got -1",
        ),
        (
            {"task": "pendulum-swing", "terms": [{"term": "forward_distance"}]},
            "terms[0]",
            "needs a model with a root position group",
        ),
        (
            {
                "task": "truck-parking",
                "terms": [{"term": "path_target", "waypoints": [{"step": 41, "target": [0] * 6}]}],
            },
            "terms[0].waypoints[0].step",
            "expected an integer in [0, 40], got 41",
        ),
        (
            {"task": "truck-parking", "initial_controls": [0, 9]},
            "initial_controls",
            "control gas must lie in its limits [-2, 5], got 9",
        ),
        (
            {"task": "truck-parking", "success": [{"check": "near", "variables": ["heading"]}]},
            "success[0].check",
            "must be one of",
        ),
        ({"task": "truck-parking", "mu_u": 0, "mu_s": 0}, "terms", "the objective is empty"),
        ({"task": "truck-parking", "colour": "red"}, "colour", "unknown key; a job takes"),
        ({"model": "pendulum-passive"}, "model", "has no controls"),
        ({"task": "truck-parking", "horizon": True}, "horizon", "expected an integer in [1, 1000], got True"),
        ({"task": "truck-parking", "horizon": "40"}, "horizon", "expected an integer in [1, 1000], got '40'"),
        ({"task": "truck-parking", "mu_u": "0.1"}, "mu_u", "got '0.1'"),
        ({"task": "truck-parking", "optimizer": {"starts": True}}, "optimizer.starts", "got True"),
        (
            {"task": "truck-parking", "optimizer": {"global_generations": 51}},
            "optimizer.global_generations",
            "[0, 50]",
        ),
        (
            {"task": "truck-parking", "terms": [{"term": "success_margin", "margin": 2}]},
            "terms[0].margin",
            "(0, 1]",
        ),
        ({"model": "../artifacts/lander"}, "model", "unknown model '../artifacts/lander'"),
        (
            {"task": "truck-parking", "version": "../lander/latest"},
            "version",
            "has no version '../lander/latest'",
        ),
    ],
)
def test_bad_specs_name_the_field_the_expected_and_the_got(
    spec: dict[str, Any], field: str, text: str
) -> None:
    err = error_of(spec)
    assert err.field == field
    assert text in str(err), str(err)
    assert str(err).startswith(f"{field}: ")


def test_validate_job_imports_neither_torch_nor_mujoco() -> None:
    code = (
        "import sys; from pathlib import Path; from neuroanimator.control.validation import validate_job; "
        "from neuroanimator.catalog.tasks import TASKS; "
        f"validate_job({{'task': 'lander-landing'}}, Path({str(ARTIFACTS)!r})); "
        "[TASKS[t].to_dict() for t in TASKS]; "
        "bad = [m for m in ('torch', 'mujoco', 'onnxruntime') if m in sys.modules]; "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, timeout=60)


@pytest.mark.parametrize("name", sorted(TASKS))
def test_tasks_are_plain_data_with_their_criterion_in_the_description(name: str) -> None:
    task = TASKS[name]
    data = task.to_dict()
    json.dumps(data)
    assert data["horizon"] == 40 and data["substeps"] == 50
    assert data["success_criterion"] in data["description"]
    # dolphin-swim has none: as far as it can
    assert data["success_criterion"].startswith("at the end: ") or (
        not task.success and data["success_criterion"] == "no success criterion"
    )
    for key in (
        "name",
        "model",
        "initial_state",
        "target_state",
        "state_weights",
        "mu_u",
        "mu_s",
        "terms",
        "optimizer",
    ):
        assert key in data
    validate_job({"task": name}, ARTIFACTS)


THESIS_TASKS = ["pendulum-swing", "lander-landing", "truck-parking"]


def test_thesis_control_variable_counts() -> None:
    """Pendulum 60 (20 per joint), lander 80, truck 40 (thesis 6.2)."""
    assert TASKS["pendulum-swing"].control_variables(3) == 60
    assert TASKS["lander-landing"].control_variables(4) == 80
    assert TASKS["truck-parking"].control_variables(2) == 40
    assert {TASKS[t].optimizer["learning_rate"] for t in THESIS_TASKS} == {2.0, 1.5}
    assert TASKS["dolphin-swim"].control_variables(6) == 60  # thesis 6.3: a point every 2 s


def test_the_registry_collects_every_systems_tasks_once(monkeypatch: pytest.MonkeyPatch) -> None:
    from neuroanimator.catalog import tasks

    assert list(tasks.collect()) == [*THESIS_TASKS, "dolphin-swim"]
    assert all(t in s.TASKS for s in catalog.SYSTEMS for t in s.TASKS if t.name in TASKS)
    pendulum = catalog.SYSTEMS[0]
    monkeypatch.setattr(catalog, "SYSTEMS", (*catalog.SYSTEMS, pendulum))
    with pytest.raises(ValueError, match="task 'pendulum-swing' is defined twice"):
        tasks.collect()


def test_task_info_keeps_its_json_form() -> None:
    """GET /tasks shows checks as a job writes them: no null bounds or targets."""
    data = TASKS["lander-landing"].to_dict()
    assert data["success"][2] == {"check": "range", "variables": ["velocity.z"], "min": -1.0, "max": 0.0}
    assert data["state_labels"][:3] == ["position.x", "position.y", "position.z"]
    assert data["initial_controls"][0] == pytest.approx(16.2)


HUGE = 10**330  # what JSON's 1 followed by 330 zeros parses to: an integer no float can hold
ZEROS6 = [0, 0, 0, 0, 0, 0]


@pytest.mark.parametrize(
    ("spec", "field"),
    [
        (
            {"task": "truck-parking", "success": [{"check": "abs", "variables": ["heading"], "max": HUGE}]},
            "success[0].max",
        ),
        (
            {
                "task": "truck-parking",
                "success": [{"check": "abs", "variables": ["heading"], "max": 1, "target": ["a"]}],
            },
            "success[0].target[0]",
        ),
        (
            {
                "task": "truck-parking",
                "success": [{"check": "abs", "variables": ["heading"], "max": 1, "target": [[1, 2]]}],
            },
            "success[0].target[0]",
        ),
        (
            {
                "task": "truck-parking",
                "success": [{"check": "range", "variables": ["heading"], "min": 2, "max": 1}],
            },
            "success[0].min",
        ),
        (
            {"task": "truck-parking", "success": [{"check": "norm", "variables": ["heading"] * 7, "max": 1}]},
            "success[0].variables",
        ),
        ({"task": "truck-parking", "terms": [{"term": "control_effort", "weight": HUGE}]}, "terms[0].weight"),
        (
            {"task": "truck-parking", "terms": [{"term": "control_effort", "weight": 1e308}]},
            "terms[0].weight",
        ),
        (
            {
                "task": "truck-parking",
                "terms": [{"term": "path_target", "waypoints": [{"time": 1e308, "target": ZEROS6}]}],
            },
            "terms[0].waypoints[0].time",
        ),
        (
            {
                "task": "truck-parking",
                "terms": [{"term": "path_target", "waypoints": [{"time": HUGE, "target": ZEROS6}]}],
            },
            "terms[0].waypoints[0].time",
        ),
        (
            {
                "task": "truck-parking",
                "terms": [{"term": "path_target", "waypoints": [{"step": 1, "target": ZEROS6}] * 42}],
            },
            "terms[0].waypoints",
        ),
        (
            {
                "task": "truck-parking",
                "terms": [{"term": "path_target", "waypoints": [{"step": 1, "target": [1e308] * 6}]}],
            },
            "terms[0].waypoints[0].target[0]",
        ),
        (
            {"task": "truck-parking", "terms": [{"term": "forward_distance", "direction": [1e308, 1e308]}]},
            "terms[0].direction[0]",
        ),
        (
            {"task": "truck-parking", "terms": [{"term": "final_velocity", "variables": [0] * 7}]},
            "terms[0].variables",
        ),
        (
            {"task": "truck-parking", "terms": [{"term": "stay_within_bounds", "variable": 0, "low": -HUGE}]},
            "terms[0].low",
        ),
        ({"task": "truck-parking", "initial_state": [1e308, 1e308, 0, 0, 0, 0]}, "initial_state[0]"),
        ({"task": "truck-parking", "target_state": [0, HUGE, 0, 0, 0, 0]}, "target_state[1]"),
        ({"task": "truck-parking", "state_weights": [1, 1, 1e300, 1, 1, 1]}, "state_weights[2]"),
        ({"task": "truck-parking", "initial_controls": [HUGE, 0]}, "initial_controls[0]"),
        ({"task": "truck-parking", "horizon": HUGE}, "horizon"),
        ({"task": "truck-parking", "horizon": math.inf}, "horizon"),
        ({"task": "truck-parking", "mu_u": HUGE}, "mu_u"),
        ({"task": "truck-parking", "optimizer": {"learning_rate": HUGE}}, "optimizer.learning_rate"),
    ],
)
def test_hostile_numbers_and_lengths_are_refused_naming_the_field(spec: dict[str, Any], field: str) -> None:
    """Huge integers, 1e308 and lists longer than the model are refused before a worker sees them:
    a spec that validates is one a worker can run (each of these once raised in the API or failed
    in every retry of the worker)."""
    err = error_of(spec)
    assert err.field == field, str(err)
    assert len(str(err)) < 400, "a message quotes a huge input cut short"


def test_a_direction_of_huge_components_is_refused_and_a_valid_one_stays_unit() -> None:
    spec = validate_job(
        {"task": "truck-parking", "terms": [{"term": "forward_distance", "direction": [1e4, 1e4]}]}, ARTIFACTS
    )
    direction = spec.terms[0].direction  # type: ignore[union-attr]
    assert direction == pytest.approx([math.sqrt(0.5)] * 2)
    assert validate_job(spec, ARTIFACTS) == spec
