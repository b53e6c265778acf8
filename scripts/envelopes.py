"""Write the training envelope into the manifests of artifact versions trained before it existed.

    python scripts/envelopes.py [--artifacts artifacts] [--examples 20000] [--force]

An emulator trained now has the envelope of its training states in its manifest (``envelope``, from
``neuroanimator/training/envelope.py``). For an older version this regenerates its training data (the same
sampler, seed and super-step, so these are the first ``--examples`` of the examples it was trained
on), computes the envelope of their states and next states, and adds it to ``manifest.json``; the
rest of the file is left as it is, byte for byte.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from neuroanimator.artifacts import registry
from neuroanimator.sim import sampling
from neuroanimator.training.envelope import training_envelope

log = logging.getLogger("envelopes")


def add_envelope(path: Path, examples: int, force: bool) -> bool:
    """Add the envelope to the manifest of the version folder ``path``; False if it had one."""
    manifest = registry.read_manifest(path)
    if manifest.envelope is not None and not force:
        return False
    physical = registry.load_physical_model(path, manifest)
    count = min(examples, manifest.metrics.examples)
    cfg = manifest.train_config
    data = sampling.generate(
        physical, manifest.substeps, count, cfg.seed, progress=False, sampler=cfg.sampler
    )
    envelope = training_envelope(
        manifest.state_layout(),
        np.concatenate([data.states, data.next_states]),
        manifest.frame.translate,
        manifest.frame.rotate,
    )
    file = path / registry.MANIFEST_FILE
    text = file.read_text()
    raw = json.loads(text)
    block = json.dumps([g.model_dump() for g in envelope], indent=2).replace("\n", "\n  ")
    if "envelope" in raw:  # --force: rewrite the whole file (the key is somewhere inside)
        raw["envelope"] = json.loads(block)
        text = json.dumps(raw, indent=2, ensure_ascii=False) + "\n"
    else:  # insert before the closing brace: every other byte stays
        body = text.rstrip()
        assert body.endswith("}"), f"{file} does not end with a JSON object"
        text = body[:-1].rstrip() + f',\n  "envelope": {block}\n}}\n'
    file.write_text(text)
    registry.read_manifest(path)  # still a valid manifest
    return True


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--artifacts", type=Path, default=Path("artifacts"))
    p.add_argument("--examples", type=int, default=20_000, help="training examples regenerated per version")
    p.add_argument("--force", action="store_true", help="recompute envelopes that are there already")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for model in registry.list_models(args.artifacts):
        for version in registry.versions(args.artifacts, model):
            t0 = time.perf_counter()
            done = add_envelope(args.artifacts / model / version, args.examples, args.force)
            what = f"envelope written ({time.perf_counter() - t0:.0f} s)" if done else "has an envelope"
            log.info("%s/%s: %s", model, version, what)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
