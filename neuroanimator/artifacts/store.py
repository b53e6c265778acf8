"""The artifact registry, write side (and the torch emulator of an artifact): needs torch.

``save`` writes a trained emulator as a new version folder (the files and pointers described in
``neuroanimator.artifacts.registry``, which finds and reads them), ``save_tuned`` one fine-tuned for a
policy (no pointer moves). A version folder is renamed into place only when complete, and pointers are
replaced atomically, so a crash never leaves a half-written version marked latest. ``load_torch``
rebuilds the torch emulator of a version (the same weights as its ONNX graph) for the processes that
differentiate through it.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import os
import shutil
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from neuroanimator.artifacts import registry
from neuroanimator.core.manifest import (
    ControlInput,
    EmulatorGraph,
    EnvelopeGroup,
    GraphInput,
    GraphIO,
    Hashes,
    InputGroup,
    Manifest,
    ModelAsset,
    Network,
    NetworkClearance,
    NetworkFrame,
    NetworkLimit,
    NetworkReads,
    Normalization,
    Symmetries,
    TrainMetrics,
    Tuning,
)
from neuroanimator.emulator.articulated import (
    TRUNK,
    ArticulatedCore,
    articulated_core,
    branch_geoms,
    make_articulated,
)
from neuroanimator.emulator.clearance import Clearance
from neuroanimator.emulator.hierarchy import GLOBAL, VECTORS, HierarchicalEmulator
from neuroanimator.emulator.regularizer import regularization
from neuroanimator.emulator.structured import FrameConfig, JointLimit, StructuredEmulator
from neuroanimator.export.onnx import to_onnx
from neuroanimator.sim.model import ModelError, PhysicalModel
from neuroanimator.training.hierarchy import HierarchyResult
from neuroanimator.training.train import TrainResult

CORE = "core"  # the network of a one-network emulator (StructuredEmulator.core)


def describe_network(emu: StructuredEmulator, model: PhysicalModel, mode: str) -> Network:
    """The manifest's description of a one-network emulator: ``core`` in the root frame, writing every
    state group; ``mode`` is the normalisation mode it was fitted with."""
    read = {name for name, _ in emu.input_groups}
    fr = emu.frame
    return _describe(
        emu,
        mode,
        name=CORE,
        frame=NetworkFrame(
            translate=list(fr.translate),
            rotate=fr.rotate,
            force_pairs=[list(p) for p in fr.force_pairs],
            control_pairs=[list(p) for p in fr.control_pairs],
            body=emu.architecture()["frame"]["body"],  # type: ignore[index]
            slides=list(fr.slides),
        ),
        reads=NetworkReads(
            state=[g.name for g in model.layout if g.name in read],
            controls=list(model.control_names) if "controls" in read else [],
            forces=list(model.force_names) if "forces" in read else [],
        ),
        writes=[g.name for g in model.layout],
    )


def describe_hierarchy(emu: HierarchicalEmulator, model: PhysicalModel, mode: str) -> EmulatorGraph:
    """The manifest's description of a hierarchical emulator: ``global`` writing every part's frame
    quantities, then one network per part, in its frame, reading its groups, its neighbours' points
    and its predicted frame."""
    controls = list(model.control_names)
    points = {g for p in emu.parts for pt in p.points for g in pt}
    networks = [
        _describe(
            emu.glob,
            mode,
            name=GLOBAL,
            frame=NetworkFrame(),
            reads=NetworkReads(state=[g.name for g in model.layout if g.name in points], controls=controls),
            writes=[g.name for g in emu.glob.layout],
        )
    ]
    for part, (name, net) in zip(emu.parts, emu.networks[1:], strict=True):
        networks.append(
            _describe(
                net,
                mode,
                name=name,
                frame=NetworkFrame(part=name),
                reads=NetworkReads(
                    state=[*part.groups, *(g for pt in part.neighbours for g in pt)],
                    predicted=[f"{name}.{q}" for q in VECTORS],
                    controls=controls,
                ),
                writes=list(part.groups),
            )
        )
    return EmulatorGraph(
        networks=networks,
        stages=[[GLOBAL], [p.name for p in emu.parts]],
        parts=list(emu.parts),
        regularizer=None if emu.regularizer is None else emu.regularizer.spec,
    )


def describe_articulated(emu: StructuredEmulator, model: PhysicalModel, mode: str) -> EmulatorGraph:
    """The manifest's description of an articulated hierarchy (``neuroanimator.emulator.articulated``): the trunk
    network, then one network per branch, all in the root frame; a branch reads the trunk's predicted
    change of the trunk's groups. Each network's normalisation is its slice of the emulator's."""
    core = articulated_core(emu)
    assert core is not None
    parts = _Articulated(emu, core, describe_network(emu, model, mode), mode)
    return EmulatorGraph(
        networks=[parts.trunk(), *(parts.branch(model, k) for k in range(len(core.branches)))],
        stages=[[TRUNK], [b.name for b in core.branches]],
        regularizer=None if emu.regularizer is None else emu.regularizer.spec,
    )


@dataclass(frozen=True)
class _Articulated:
    """What the networks of an articulated hierarchy's description share: the emulator ``emu``, its
    core, ``base`` (the emulator described as one network: its frame, reads, limits, clearance and
    input groups) and the normalisation ``mode``."""

    emu: StructuredEmulator
    core: ArticulatedCore
    base: Network
    mode: str

    def trunk(self) -> Network:
        """The trunk: every input of the emulator, writing the trunk's groups."""
        base, core = self.base, self.core
        return self.network(
            TRUNK, core.trunk_hidden, core.trunk, core.output_columns()[TRUNK], base.reads,
            list(core.trunk_writes), list(range(self.emu.input_size)), list(base.normalization.input_groups),
            base.clearance,
        )  # fmt: skip

    def branch(self, model: PhysicalModel, k: int) -> Network:
        """Branch k: the emulator's input columns it reads (``ArticulatedCore.input_columns``), by
        group, then the trunk's change; the clearance of its own geoms."""
        emu, core = self.emu, self.core
        b = core.branches[k]
        starts, at = {}, 0  # each input group's first column and width
        for group, width in emu.input_groups:
            starts[group] = (at, width)
            at += width
        sel = core.input_columns(k)  # the emulator's input columns it reads, in order
        groups = []
        for group, (start, width) in starts.items():
            n = sum(1 for c in sel if start <= c < start + width)
            if n:
                groups.append(InputGroup(name=group, size=n))
        groups.append(InputGroup(name=f"{TRUNK}.change", size=len(core.output_columns()[TRUNK])))
        state_groups = [g for g in [*b.groups, *core.trunk_writes, *b.reads] if g in starts]
        reads = NetworkReads(
            state=list(dict.fromkeys(state_groups)),
            predicted=list(core.trunk_writes),
            controls=list(model.control_names) if b.controls is None else list(b.controls),
        )
        clearance = (
            None
            if emu.clearance is None or not branch_geoms(emu, b)
            else NetworkClearance(geoms=branch_geoms(emu, b), horizon=emu.clearance.horizon)
        )
        return self.network(
            b.name, core.branch_hidden, core.branch_net(k), core.output_columns()[b.name], reads,
            list(b.groups), sel, groups, clearance,
        )  # fmt: skip

    def network(self, name: str, hidden: tuple[int, ...], net: torch.nn.Module, cols: list[int], reads: NetworkReads,
                writes: list[str], inputs: list[int], groups: list[InputGroup],
                clearance: NetworkClearance | None) -> Network:  # fmt: skip
        """One network: its slice of the emulator's normalisation (the emulator's ``inputs`` and output
        columns ``cols``; a branch's trunk-change inputs unscaled)."""
        emu, trunk_cols = self.emu, self.core.output_columns()[TRUNK]
        norm = Normalization(
            mode=self.mode,  # checked by the manifest
            input_groups=groups,
            x_mean=[float(v) for v in emu.x_mean[inputs]] + [0.0] * (0 if name == TRUNK else len(trunk_cols)),
            x_std=[float(v) for v in emu.x_std[inputs]] + [1.0] * (0 if name == TRUNK else len(trunk_cols)),
            y_mean=[float(v) for v in emu.y_mean[cols]],
            y_std=[float(v) for v in emu.y_std[cols]],
        )
        return Network(
            name=name,
            frame=self.base.frame,
            reads=reads,
            writes=writes,
            hidden=list(hidden),
            activation=emu.activation,  # checked by the manifest
            normalization=norm,
            input_size=len(norm.x_mean),
            output_size=len(cols),
            weights=sum(p.numel() for p in net.parameters()),
            skip=True,
            limits=self.base.limits if name == TRUNK else [],
            clearance=clearance,
            members=self.core.members,
        )


def _describe(
    emu: StructuredEmulator, mode: str, name: str, frame: NetworkFrame, reads: NetworkReads, writes: list[str]
) -> Network:
    """One network of an emulator as the manifest lists it (sizes, normalisation, limits from ``emu``)."""
    return Network(
        name=name,
        frame=frame,
        reads=reads,
        writes=writes,
        hidden=list(emu.hidden),
        activation=emu.activation,  # checked by the manifest
        normalization=Normalization(
            mode=mode,  # checked by the manifest
            input_groups=[InputGroup(name=name, size=size) for name, size in emu.input_groups],
            x_mean=emu.x_mean.tolist(),
            x_std=emu.x_std.tolist(),
            y_mean=emu.y_mean.tolist(),
            y_std=emu.y_std.tolist(),
        ),
        input_size=emu.input_size,
        output_size=emu.layout.size,
        weights=sum(p.numel() for p in emu.parameters()),
        skip=emu.skip is not None,
        limits=[
            NetworkLimit(
                position=lim.position,
                velocity=lim.velocity,
                low=lim.low,
                high=lim.high,
                horizon=emu.horizon,
                margin=lim.margin,
            )
            for lim in emu.limits
        ],
        clearance=None
        if emu.clearance is None
        else NetworkClearance(
            geoms=list(emu.clearance.geoms),
            pairs=list(emu.clearance.pairs),
            tendons=list(emu.clearance.tendons),
            horizon=emu.clearance.horizon,
        ),
    )


def asset_kinds(xml: str) -> dict[str, Literal["mesh", "texture", "hfield", "skin"]]:
    """Which kind of asset each file the MJCF names is (``file`` of a mesh, height field, skin, texture,
    and a texture's cube faces ``file*``)."""
    kinds: dict[str, Literal["mesh", "texture", "hfield", "skin"]] = {}
    for el in ET.fromstring(xml).iter():
        if el.tag in ("mesh", "hfield", "skin", "texture"):
            for key, value in el.attrib.items():
                if key.startswith("file") and value:
                    kinds[value] = el.tag  # type: ignore[assignment]
    return kinds


def describe_assets(model: PhysicalModel) -> list[ModelAsset]:
    """The manifest's list of the files a model's MJCF names, by content (``ModelAsset``)."""
    kinds = asset_kinds(model.xml) if model.assets else {}
    out = []
    for name, data in sorted(model.assets.items()):
        if name not in kinds:
            raise ModelError(f"model {model.name}: asset {name!r} is not named by its MJCF")
        sha = hashlib.sha256(data).hexdigest()
        if not name.startswith(sha):
            raise ModelError(f"model {model.name}: asset {name!r} is not named by its content ({sha})")
        source = model.asset_sources.get(name, "")
        out.append(ModelAsset(name=name, sha256=sha, kind=kinds[name], size=len(data), source=source))
    return out


def write_assets(model_dir: Path, model: PhysicalModel) -> None:
    """Store the model's assets in ``<model>/assets/`` by content: a file already there is the same
    file (its name is its hash), so versions share it; a new one appears whole or not at all."""
    _write_asset_files(model_dir, model.assets)


def _write_asset_files(model_dir: Path, assets: dict[str, bytes]) -> None:
    if not assets:
        return
    folder = model_dir / registry.ASSETS_DIR
    folder.mkdir(exist_ok=True)
    for name, data in assets.items():
        target = folder / name
        if target.is_file() and target.stat().st_size == len(data):
            continue
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-asset-")
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, target)


def build_manifest(
    model: PhysicalModel,
    result: TrainResult | HierarchyResult,
    version: str,
    onnx_sha256: str,
    created: dt.datetime,
) -> Manifest:
    """The manifest of a trained emulator of ``model`` saved as ``version``."""
    cfg = result.config
    inputs: list[GraphInput] = ["state"]
    inputs += ["controls"] if model.num_controls else []
    inputs += ["forces"] if model.num_forces else []
    return Manifest(
        model=model.name,
        version=version,
        created=created.isoformat(timespec="seconds"),
        substeps=cfg.substeps,
        timestep=model.dt,
        super_timestep=model.dt * cfg.substeps,
        description=model.spec.description,
        state_size=model.state_size,
        layout=model.layout.placed(),
        state_labels=model.layout.labels(),
        controls=[
            ControlInput(
                name=n,
                low=float(lo),
                high=float(hi),
                limit_low=float(a),
                limit_high=float(b),
                **info.model_dump(),
            )
            for n, (lo, hi), (a, b), info in zip(
                model.control_names,
                model.control_range,
                model.control_limits,
                model.control_info,
                strict=True,
            )
        ],
        forces=list(model.spec.forces),
        frame=Symmetries(
            translate=list(model.frame.translate), rotate=model.frame.rotate, slides=list(model.frame.slides)
        ),
        io=GraphIO(inputs=inputs),
        emulator=describe_hierarchy(result.emulator, model, cfg.normalization)
        if isinstance(result.emulator, HierarchicalEmulator)
        else describe_articulated(result.emulator, model, cfg.normalization)
        if articulated_core(result.emulator) is not None
        else EmulatorGraph(
            networks=[describe_network(result.emulator, model, cfg.normalization)],
            stages=[[CORE]],
            regularizer=None if result.emulator.regularizer is None else result.emulator.regularizer.spec,
        ),
        train_config=cfg,
        metrics=TrainMetrics(**result.metrics),
        hashes=Hashes(
            mjcf_sha256=model.mjcf_sha256(),
            training_data_sha256=result.data_sha256,
            onnx_sha256=onnx_sha256,
        ),
        spec=model.spec,
        assets=describe_assets(model),
        envelope=result.envelope,
    )


def save(root: Path, model: PhysicalModel, result: TrainResult | HierarchyResult) -> Path:
    """Write a trained emulator as a new version of ``model``; returns the version folder."""
    problem = registry.name_problem(model.name)
    if problem is not None:
        raise ModelError(problem)
    substeps = result.config.substeps
    model_dir = root / model.name
    model_dir.mkdir(parents=True, exist_ok=True)
    now = dt.datetime.now(dt.UTC)
    repeat = 1
    while (model_dir / registry.version_name(substeps, now, repeat)).exists():
        repeat += 1
    version = registry.version_name(substeps, now, repeat)
    onnx_bytes = to_onnx(result.emulator)
    manifest = build_manifest(model, result, version, hashlib.sha256(onnx_bytes).hexdigest(), now)
    write_assets(model_dir, model)  # before the version appears: a version always has its assets
    tmp = Path(tempfile.mkdtemp(dir=model_dir, prefix=f".tmp-{version}-"))
    try:
        (tmp / registry.ONNX_FILE).write_bytes(onnx_bytes)
        torch.save(result.emulator.state_dict(), tmp / registry.WEIGHTS_FILE)
        np.save(tmp / registry.LINEAR_FILE, result.linear)
        (tmp / registry.MJCF_FILE).write_text(model.xml)
        (tmp / registry.MANIFEST_FILE).write_text(manifest.model_dump_json(indent=2) + "\n")
        os.rename(tmp, model_dir / version)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    registry.write_pointer(model_dir, registry.pointer_name(substeps), version)
    if substeps == model.spec.substeps or not (model_dir / registry.pointer_name()).exists():
        registry.write_pointer(model_dir, registry.pointer_name(), version)
    return model_dir / version


def widened_envelope(manifest: Manifest, low: np.ndarray, high: np.ndarray) -> list[EnvelopeGroup] | None:
    """``manifest``'s envelope with each bounded value widened to (S,) ``low`` and ``high`` (the states
    an emulator was fine-tuned on); a value the emulator is indifferent to stays unbounded."""
    if manifest.envelope is None:
        return None
    offsets = {g.name: g.offset for g in manifest.layout}
    out = []
    for env in manifest.envelope:
        at = offsets[env.group]
        out.append(
            EnvelopeGroup(
                group=env.group,
                low=[None if lo is None else min(lo, float(low[at + i])) for i, lo in enumerate(env.low)],
                high=[None if hi is None else max(hi, float(high[at + i])) for i, hi in enumerate(env.high)],
            )
        )
    return out


def save_tuned(
    root: registry.Root,
    base: Path,
    emulator: StructuredEmulator,
    tuning: Tuning,
    envelope: tuple[np.ndarray, np.ndarray] | None = None,
) -> Path:
    """Write ``emulator``, fine-tuned from the version at ``base`` for a policy, as a new version of its
    model in ``root``'s data directory (``<base version>-tuned-<UTC time>``; the model's assets copied
    there when the base is a read-only default). No pointer moves: the policy names the version.
    ``envelope``: (S,) lows and highs of the states it was fine-tuned on, widening the base's.
    Returns the version folder."""
    manifest = registry.read_manifest(base)
    model_dir = registry.writable(root) / manifest.model
    model_dir.mkdir(parents=True, exist_ok=True)
    now = dt.datetime.now(dt.UTC)
    stamp = now.strftime("%Y%m%dT%H%M%S")
    version, repeat = f"{manifest.version}-tuned-{stamp}", 1
    while (model_dir / version).exists():
        repeat += 1
        version = f"{manifest.version}-tuned-{stamp}-{repeat}"
    onnx_bytes = to_onnx(emulator)
    tuned = manifest.model_copy(
        update={
            "version": version,
            "created": now.isoformat(timespec="seconds"),
            "hashes": manifest.hashes.model_copy(
                update={"onnx_sha256": hashlib.sha256(onnx_bytes).hexdigest()}
            ),
            "envelope": manifest.envelope if envelope is None else widened_envelope(manifest, *envelope),
            "tuned": tuning,
        }
    )
    _write_asset_files(model_dir, registry.read_assets(base, manifest))
    tmp = Path(tempfile.mkdtemp(dir=model_dir, prefix=f".tmp-{version}-"))
    try:
        (tmp / registry.ONNX_FILE).write_bytes(onnx_bytes)
        torch.save(emulator.state_dict(), tmp / registry.WEIGHTS_FILE)
        shutil.copyfile(base / registry.LINEAR_FILE, tmp / registry.LINEAR_FILE)
        shutil.copyfile(base / registry.MJCF_FILE, tmp / registry.MJCF_FILE)
        (tmp / registry.MANIFEST_FILE).write_text(tuned.model_dump_json(indent=2) + "\n")
        os.rename(tmp, model_dir / version)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return model_dir / version


def load_torch(path: Path) -> StructuredEmulator:
    """The torch emulator of an artifact (same weights as its ONNX graph): one network, or an articulated
    hierarchy (one structured emulator too); ``load_hierarchy`` builds a hierarchy over parts."""
    manifest = registry.read_manifest(path)
    model = registry.load_physical_model(path, manifest)
    branches = manifest.spec.branches
    by_name = {n.name: n for n in manifest.emulator.networks}
    net = by_name[TRUNK] if branches else manifest.emulator.only()
    fr = net.frame
    emu = StructuredEmulator(
        model.layout,
        model.num_controls,
        model.num_forces,
        FrameConfig(
            translate=tuple(fr.translate),
            rotate=fr.rotate,
            force_pairs=tuple(tuple(p) for p in fr.force_pairs),
            body=fr.body,
            control_pairs=tuple(tuple(p) for p in fr.control_pairs),
            slides=tuple(fr.slides),
        ),
        tuple(net.hidden),
        net.activation,
        skip=net.skip and not branches,
        limits=[JointLimit(lim.position, lim.velocity, lim.low, lim.high, lim.margin) for lim in net.limits],
        horizon=net.limits[0].horizon if net.limits else 0.0,
        clearance=None
        if net.clearance is None
        else Clearance(
            model, net.clearance.geoms, net.clearance.horizon, net.clearance.pairs, net.clearance.tendons
        ),
    )
    if branches:
        branch_hidden = by_name[branches[0].name].hidden
        make_articulated(
            emu, branches, model.control_names, tuple(net.hidden), tuple(branch_hidden), net.members
        )
    emu.load_state_dict(torch.load(path / registry.WEIGHTS_FILE, weights_only=True))
    emu.regularizer = regularization(model.layout, manifest.emulator.regularizer, model.num_controls)
    return emu.eval()


def load_hierarchy(path: Path) -> HierarchicalEmulator:
    """The torch emulator of an artifact whose emulator is a hierarchy over parts (``describe_hierarchy``)."""
    manifest = registry.read_manifest(path)
    graph = manifest.emulator
    if not graph.parts:
        raise ValueError(f"{path}: this emulator is not a hierarchy over parts")
    model = registry.load_physical_model(path, manifest)
    by_name = {n.name: n for n in graph.networks}
    glob, local = by_name[GLOBAL], by_name[graph.parts[0].name]
    emu = HierarchicalEmulator(
        model.layout,
        model.num_controls,
        graph.parts,
        tuple(glob.hidden),
        tuple(local.hidden),
        glob.activation,
        skip=glob.skip,
    )
    emu.load_state_dict(torch.load(path / registry.WEIGHTS_FILE, weights_only=True))
    emu.regularizer = regularization(model.layout, graph.regularizer, model.num_controls)
    return emu.eval()


def load_emulator(path: Path) -> StructuredEmulator | HierarchicalEmulator:
    """The torch emulator of an artifact, whichever its structure."""
    return load_hierarchy(path) if registry.read_manifest(path).emulator.parts else load_torch(path)
