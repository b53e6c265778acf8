"""The manifest: every committed artifact reads (format 1, upgraded), unknown formats are refused
naming the file and the formats read, and the emulator description can say a hierarchy."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

from neuroanimator.artifacts import registry
from neuroanimator.core.manifest import (
    FORMAT,
    READABLE_FORMATS,
    Manifest,
    ManifestError,
    Network,
    parse_manifest,
)
from neuroanimator.core.state import StateLayout
from neuroanimator.sim.model import derive_layout

ROOT = Path(__file__).resolve().parents[1]
ARTIFACTS = ROOT / "artifacts"
COMMITTED_ALL = sorted(p.parent for p in ARTIFACTS.glob("*/*/manifest.json"))
# one-network emulators; the hierarchies (the dolphin) are checked on their own below
COMMITTED = [p for p in COMMITTED_ALL if len(registry.read_manifest(p).emulator.networks) == 1]
HIERARCHIES = [p for p in COMMITTED_ALL if p not in COMMITTED and registry.read_manifest(p).emulator.parts]
ARTICULATED = [
    p for p in COMMITTED_ALL if p not in COMMITTED and not registry.read_manifest(p).emulator.parts
]

# A body with a free root and two hinged arms: the shape of a hierarchy (one network for the body,
# then one per arm in the arm's frame).
TWO_ARMS = """<mujoco model="two-arms">
  <worldbody>
    <body name="torso" pos="0 0 1">
      <freejoint name="root"/>
      <geom type="box" size="0.2 0.1 0.3" mass="5"/>
      <body name="arm_l" pos="0 0.2 0.2"><joint name="shoulder_l" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/></body>
      <body name="arm_r" pos="0 -0.2 0.2"><joint name="shoulder_r" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/></body>
    </body>
  </worldbody>
</mujoco>"""


def _committed(path: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((path / "manifest.json").read_text())
    return data


def _network(
    name: str, reads: dict[str, list[str]], writes: list[str], layout: StateLayout
) -> dict[str, Any]:
    out = sum(layout.groups[[g.name for g in layout].index(w)].size for w in writes)
    return {
        "name": name,
        "frame": {"part": None if name == "body" else name, "translate": [True, True, False], "rotate": True},
        "reads": reads,
        "writes": writes,
        "hidden": [32],
        "activation": "tanh",
        "normalization": {
            "mode": "group",
            "input_groups": [{"name": "inputs", "size": 4}],
            "x_mean": [0.0] * 4,
            "x_std": [1.0] * 4,
            "y_mean": [0.0] * out,
            "y_std": [1.0] * out,
        },
        "input_size": 4,
        "output_size": out,
        "weights": 32 * 4 + 32 + 32 * out + out,
    }


def _hierarchy(stages: list[list[str]] | None = None, **changes: Any) -> dict[str, Any]:
    """A format-2 manifest of the two-armed body: the body network, then one network per arm."""
    import mujoco

    layout = derive_layout(mujoco.MjModel.from_xml_string(TWO_ARMS))
    data = parse_manifest(_committed(COMMITTED[0])).model_dump(mode="json")
    body = ["root.pos", "root.quat", "root.vel", "root.angvel"]
    root_frame = ["root.quat", "root.angvel"]
    networks = [
        _network("body", {"state": body[1:]}, body, layout),
        *(
            _network(
                f"arm_{side}",
                {"state": [f"shoulder_{side}.angle", f"shoulder_{side}.rate"], "predicted": root_frame},
                [f"shoulder_{side}.angle", f"shoulder_{side}.rate"],
                layout,
            )
            for side in "lr"
        ),
    ]
    data |= {
        "state_size": layout.size,
        "layout": [g.model_dump(mode="json") for g in layout.placed()],
        "state_labels": layout.labels(),
        "controls": [],
        "emulator": {"networks": networks, "stages": stages or [["body"], ["arm_l", "arm_r"]]},
        "envelope": None,  # the committed one is of another layout
    }
    return data | changes


@pytest.mark.parametrize("path", COMMITTED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_committed_manifest_reads_as_one_network(path: Path) -> None:
    raw = _committed(path)
    assert raw["format"] in (1, FORMAT)  # the committed artifacts are read as written (format 1 upgraded)
    m = registry.read_manifest(path)
    assert (m.format, m.model, m.version) == (FORMAT, path.parent.name, path.name)
    net = m.emulator.only()
    assert m.emulator.stages == [[net.name]]
    assert net.writes == [g.name for g in m.layout]
    assert set(net.reads.state) <= {g.name for g in m.layout}
    assert net.reads.controls == [c.name for c in m.controls]
    assert m.state_layout().size == m.state_size == len(m.state_labels)
    # trained before there was a choice of sampler or a time budget: spaced examples, no budget
    assert m.train_config.sampler == raw["train_config"].get("sampler", "spaced")
    assert m.train_config.time_budget == raw["train_config"].get("time_budget")
    if raw["format"] == FORMAT:
        written = raw["emulator"]["networks"][0]
        # fields added later read as their defaults
        later: dict[str, Any] = {f: True for f in {"limits", "clearance", "members"} - set(written)}
        added = {"control_pairs", "slides"} - set(written["frame"])
        if added:
            later["frame"] = added
            assert all(getattr(net.frame, f) == [] for f in added)
        assert net.model_dump(mode="json", exclude=later) == written
        assert all(getattr(net, f) == Network.model_fields[f].default for f in later if f != "frame")
        return
    assert net.hidden == raw["architecture"]["hidden"] and net.weights == raw["architecture"]["weights"]
    assert net.normalization.x_mean == raw["normalization"]["x_mean"]
    assert net.input_size == len(net.normalization.x_mean) == raw["architecture"]["input_size"]
    assert net.frame.translate == raw["architecture"]["frame"]["translate"]
    # format 1 was trained in the heading frame, without the linear path or the rollout phase
    assert not net.frame.body and not net.skip
    assert (m.train_config.frame, m.train_config.skip, m.train_config.rollout_steps) == ("heading", False, 0)


@pytest.mark.parametrize("path", HIERARCHIES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_committed_hierarchy_reads_as_its_stages(path: Path) -> None:
    """A committed hierarchy: the global network first, then one per part, together writing the state."""
    m = registry.read_manifest(path)
    assert (m.format, m.model, m.version) == (FORMAT, path.parent.name, path.name)
    graph = m.emulator
    parts = [p.name for p in graph.parts]
    assert graph.stages == [["global"], parts] and [n.name for n in graph.networks] == ["global", *parts]
    assert sorted(graph.written) == sorted(g.name for g in m.layout)
    assert all(n.reads.controls == [c.name for c in m.controls] for n in graph.networks)
    assert m.state_layout().size == m.state_size == len(m.state_labels)


def test_the_dolphin_is_the_committed_hierarchy() -> None:
    assert [p.parent.name for p in HIERARCHIES] == ["dolphin"]


@pytest.mark.parametrize("path", ARTICULATED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_committed_articulated_hierarchy_reads_as_its_stages(path: Path) -> None:
    """A committed articulated hierarchy (the runner): the trunk, then one network per branch, together
    writing the state once, each branch reading the trunk's prediction and its own controls."""
    m = registry.read_manifest(path)
    graph = m.emulator
    branches = [b.name for b in m.spec.branches]
    assert graph.stages == [["trunk"], branches] and [n.name for n in graph.networks] == ["trunk", *branches]
    assert sorted(graph.written) == sorted(g.name for g in m.layout)
    trunk = graph.networks[0]
    for net, branch in zip(graph.networks[1:], m.spec.branches, strict=True):
        assert net.writes == branch.groups and net.reads.predicted == trunk.writes
        assert net.reads.controls == branch.controls
    assert [p.parent.name for p in ARTICULATED] == ["runner"]


@pytest.mark.parametrize("path", COMMITTED_ALL[:3] + HIERARCHIES + ARTICULATED, ids=lambda p: p.name)
def test_format_2_round_trips_through_json(path: Path) -> None:
    m = registry.read_manifest(path)
    again = parse_manifest(json.loads(m.model_dump_json()))
    assert again == m


@pytest.mark.parametrize("found", [0, 3, 999, None, "1", True])
def test_unknown_format_is_refused_naming_the_file_and_the_formats_read(
    tmp_path: Path, found: object
) -> None:
    (tmp_path / "manifest.json").write_text(json.dumps({**_committed(COMMITTED[0]), "format": found}))
    with pytest.raises(registry.ArtifactError) as exc:
        registry.read_manifest(tmp_path)
    text = str(exc.value)
    assert str(tmp_path / "manifest.json") in text
    assert f"format {found!r}" in text
    assert str(list(READABLE_FORMATS)) in text
    assert exc.value.what == "manifest"


def test_unreadable_or_incomplete_manifest_names_the_file(tmp_path: Path) -> None:
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(registry.ArtifactError, match="manifest"):
        registry.read_manifest(tmp_path)
    data = _committed(COMMITTED[0])
    del data["hashes"]
    (tmp_path / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(
        registry.ArtifactError, match=r"(?s)manifest\.json: not a valid format-\d manifest.*hashes"
    ):
        registry.read_manifest(tmp_path)


def test_a_hierarchy_of_networks_is_a_valid_description() -> None:
    m = Manifest.model_validate(_hierarchy())
    assert [n.name for n in m.emulator.networks] == ["body", "arm_l", "arm_r"]
    arm = m.emulator.networks[1]
    assert arm.frame.part == "arm_l" and arm.reads.predicted == ["root.quat", "root.angvel"]
    assert sorted(m.emulator.written) == sorted(g.name for g in m.layout)
    with pytest.raises(ManifestError, match="3 networks"):
        m.emulator.only()


@pytest.mark.parametrize(
    ("stages", "message"),
    [
        ([["body", "arm_l", "arm_r"]], "reads the predicted 'root.quat', which no earlier stage writes"),
        ([["arm_l"], ["body"], ["arm_r"]], "which no earlier stage writes"),
        ([["body"], ["arm_l"]], "stages must name every network once"),
        ([["body"], ["arm_l", "arm_r", "legs"]], "stages must name every network once"),
    ],
)
def test_an_unsound_composition_is_refused(stages: list[list[str]], message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        Manifest.model_validate(_hierarchy(stages))


def test_every_state_group_is_written_exactly_once() -> None:
    data = _hierarchy()
    data["emulator"]["networks"][1]["writes"] = ["shoulder_l.angle"]
    data["emulator"]["networks"][1]["normalization"] |= {"y_mean": [0.0], "y_std": [1.0]}
    data["emulator"]["networks"][1]["output_size"] = 1
    with pytest.raises(ValidationError, match="write every state group once"):
        Manifest.model_validate(data)
    data = _hierarchy()
    data["emulator"]["networks"][2]["writes"] = ["shoulder_l.angle", "shoulder_l.rate"]
    with pytest.raises(ValidationError, match="written by 'arm_l' and 'arm_r'"):
        Manifest.model_validate(data)


def test_networks_read_only_what_the_model_has() -> None:
    data = _hierarchy()
    data["emulator"]["networks"][0]["reads"]["controls"] = ["jet"]
    with pytest.raises(ValidationError, match=r"network 'body' reads unknown controls \['jet'\]"):
        Manifest.model_validate(data)


def test_reading_manifests_and_results_imports_neither_torch_nor_mujoco() -> None:
    """Nor numpy: the dashboard's server reads results with pydantic alone."""
    code = (
        "import sys; from pathlib import Path; from neuroanimator.artifacts import registry\n"
        f"root = Path({str(ARTIFACTS)!r})\n"
        "for model in registry.list_models(root):\n"
        "    for n in registry.available_substeps(root, model):\n"
        "        registry.read_manifest(registry.resolve(root, model, substeps=n))\n"
        "    assert registry.model_eval(root, model) and registry.model_bench(root, model)\n"
        "bad = [m for m in ('torch', 'mujoco', 'onnxruntime', 'numpy') if m in sys.modules]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, timeout=120)
