#!/usr/bin/env python3
"""Random scalpel strokes on a mass-spring scene, each run as a cut script by the real
server binary, counting the cut updates that fell back to an open hole and why.

    python3 scripts/random-cuts.py [--seed 11] [--count 100] [--scene skin-patch]
        [--server target/debug/cutsim-server] [--keep DIR]

Each stroke is straight, or bent through a point near its middle (half of them), 10-80 mm
long, 3, 5 or 8 mm deep, drawn in 100, 300 or 600 steps from a point anywhere within
60 x 45 mm of the scene's centre (so many leave the default 100 x 80 mm patch through its
edge), then the button is released and the blade lifted out. The same seed gives the same
strokes. Prints one line per run with a fallback and a summary; exits 0 (a survey, not a
test: the tests in server/sim/tests/cut_robustness.rs assert what must hold).
"""

import argparse
import json
import math
import random
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path


def strokes(seed: int, count: int, scene: str):
    rng = random.Random(seed)
    for _ in range(count):
        a = [rng.uniform(-0.06, 0.06), rng.uniform(-0.045, 0.045)]
        angle = rng.uniform(0, 2 * math.pi)
        length = rng.uniform(0.01, 0.08)
        b = [a[0] + length * math.cos(angle), a[1] + length * math.sin(angle)]
        steps = rng.choice([100, 300, 600])
        depth = rng.choice([-0.003, -0.005, -0.008])
        keyframes = [{"step": 0, "position_m": [a[0], a[1], depth], "cut": True}]
        if rng.random() < 0.5:
            mid = [(a[0] + b[0]) / 2 + rng.uniform(-0.01, 0.01), (a[1] + b[1]) / 2 + rng.uniform(-0.01, 0.01)]
            keyframes.append({"step": steps // 2, "position_m": [mid[0], mid[1], depth], "cut": True})
        keyframes.append({"step": steps, "position_m": [b[0], b[1], depth], "cut": False})
        keyframes.append({"step": steps + 50, "position_m": [b[0], b[1], 0.01], "active": False})
        yield {"scene": scene, "steps": steps + 200, "tools": [{"tool": "scalpel", "keyframes": keyframes}]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--count", type=int, default=100)
    parser.add_argument("--scene", default="skin-patch", help="a bundled mass-spring scene (default skin-patch)")
    parser.add_argument("--server", default="target/debug/cutsim-server", help="the cutsim-server binary (build it with cargo build -p cutsim-server)")
    parser.add_argument("--keep", type=Path, help="write the scripts into this folder instead of a temporary one")
    args = parser.parse_args()
    if not Path(args.server).is_file():
        print(f"error: no server binary at {args.server}: build it with `cargo build -p cutsim-server` or pass --server", file=sys.stderr)
        return 2
    folder = args.keep or Path(tempfile.mkdtemp(prefix="random-cuts-"))
    folder.mkdir(parents=True, exist_ok=True)
    runs_with, updates, reasons = 0, 0, Counter()
    for k, script in enumerate(strokes(args.seed, args.count, args.scene)):
        path = folder / f"r{k:03d}.json"
        path.write_text(json.dumps(script))
        done = subprocess.run([args.server, "run", args.scene, "--script", str(path), "--json"], capture_output=True, text=True)
        if done.returncode != 0:
            print(f"error: {path}: the server exited with {done.returncode}: {done.stderr.strip()[-500:]}", file=sys.stderr)
            return 1
        report = json.loads(done.stdout.strip().splitlines()[-1])
        if report["reconstruction_fallbacks"] > 0:
            runs_with += 1
            updates += report["reconstruction_fallbacks"]
            for f in report["fallbacks"]:
                reasons[f["reason"]] += 1
            print(f"{path.name}: {report['cuts']} cuts, {report['pieces']} pieces, {report['reconstruction_fallbacks']} fallbacks: "
                  + "; ".join(f"step {f['step']}: {f['reason']}" for f in report["fallbacks"]))
    print(f"{args.count} strokes (seed {args.seed}) on {args.scene}: {runs_with} with a fallback, {updates} fallback updates")
    for reason, n in reasons.most_common():
        print(f"  {n} x {reason}")
    if args.keep is None:
        print(f"scripts in {folder}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
