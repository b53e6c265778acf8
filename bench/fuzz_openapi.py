"""Schemathesis over the three services' OpenAPI documents at length: the suite's fuzz test
(``tests/services/test_openapi_fuzz.py``: real processes, committed artifacts, a real Redis; checks
``not_a_server_error`` and ``response_schema_conformance``) with more examples per operation.

    python bench/fuzz_openapi.py [--examples 40] [--random] [--json]

Prints the cases run per service, their status codes, the 5xx count and whether every check held.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TEST = "tests/services/test_openapi_fuzz.py"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--examples", type=int, default=40, help="hypothesis examples per operation")
    p.add_argument("--random", action="store_true", help="new cases each run (default: derandomized)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "fuzz.json"
        env = {**os.environ, "FUZZ_EXAMPLES": str(args.examples), "FUZZ_REPORT": str(report)}
        if args.random:
            env["FUZZ_RANDOM"] = "1"
        t0 = time.monotonic()
        run = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", TEST],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
        )
        took = time.monotonic() - t0
        counts = json.loads(report.read_text()) if report.exists() else {}
    out = {
        "examples_per_operation": args.examples,
        "seconds": round(took, 1),
        "passed": run.returncode == 0,
        "services": {
            name: {**c, "5xx": sum(v for k, v in c["status"].items() if k.startswith("5"))}
            for name, c in counts.items()
        },
    }
    if args.json:
        print(json.dumps(out))
    else:
        print(
            f"{args.examples} examples per operation, {took:.0f} s, checks {'held' if out['passed'] else 'FAILED'}"
        )
        for name, c in out["services"].items():
            print(f"  {name}: {c['cases']} cases, {c['5xx']} 5xx, status codes {c['status']}")
    if run.returncode != 0:
        print(run.stdout[-6000:], file=sys.stderr)
    return run.returncode


if __name__ == "__main__":
    sys.exit(main())
