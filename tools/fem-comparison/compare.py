#!/usr/bin/env python3
"""cutsim's level-0 branched grid against MuJoCo's flex FEM, side by side.

The same cantilever in both: a block of 2.5 mm cells (E = 30 kPa, ν = 0.45,
ρ = 1000 kg/m³), clamped at x = 0, under gravity, no damping, a 1 ms step. MuJoCo builds it
as a 3D flexcomp grid (linear tetrahedra, six per cell) with integrator="discrete";
cutsim as a branched-grid box at level 0 (one trilinear hexahedron per cell), solved to
a relative residual of 1e-5 with each preconditioner. Both count the same nodes. Rounds
alternate between the two so that the machine's drift hits both alike; the table gives
the median over rounds of each run's median step time, and below it each round's own
ratio (MuJoCo against the best preconditioner timed right after it): on a noisy
machine the rounds' ratios show how far one run's medians can be trusted.

    python compare.py --server PATH/cutsim-server [--rounds N] [--steps N] [--out FILE]
"""

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import mujoco
import numpy as np

CELL_M = 0.0025
YOUNG_PA = 3e4
POISSON = 0.45
DENSITY = 1000.0
WARM_UP = 20
# cutsim's preconditioners, in the table's order (docs/branched-grid.md compares them).
PRECONDITIONERS = ("jacobi", "multigrid", "cholesky")

# Node counts along x, y, z: 3,321 and 936 nodes.
SIZES = [(41, 9, 9), (26, 6, 6)]


def cpu_model():
    """The CPU's model name (timings differ by about 2x between this project's hosts)."""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def mujoco_model(n):
    nx, ny, nz = n
    mass = DENSITY * (nx - 1) * (ny - 1) * (nz - 1) * CELL_M**3
    xml = f"""
<mujoco>
  <option timestep="0.001" integrator="discrete" gravity="0 0 -9.81"/>
  <worldbody>
    <flexcomp name="bar" type="grid" dim="3" count="{nx} {ny} {nz}" spacing="{CELL_M} {CELL_M} {CELL_M}"
              pos="0 0 0.5" radius="0.0005" mass="{mass}">
      <elasticity young="{YOUNG_PA}" poisson="{POISSON}" damping="0"/>
      <contact selfcollide="none" contype="0" conaffinity="0"/>
      <pin gridrange="0 0 0 0 {ny - 1} {nz - 1}"/>
    </flexcomp>
  </worldbody>
</mujoco>"""
    return mujoco.MjModel.from_xml_string(xml)


def time_mujoco(n, steps):
    model = mujoco_model(n)
    data = mujoco.MjData(model)
    for _ in range(WARM_UP):
        mujoco.mj_step(model, data)
    times = []
    for _ in range(steps):
        started = time.perf_counter()
        mujoco.mj_step(model, data)
        times.append(time.perf_counter() - started)
    return {"p50_ms": 1e3 * statistics.median(times), "nodes": int(model.nflexvert), "elements": int(model.nflexelem)}


def cutsim_scene(n, preconditioner):
    nx, ny, nz = n
    return {
        "name": f"cantilever-{nx}x{ny}x{nz}",
        "time_step_s": 0.001,
        "gravity_m_per_s2": [0, 0, -9.81],
        "model": {
            "branched-grid": {
                "volume": {"box": {"size_m": [(nx - 1) * CELL_M, (ny - 1) * CELL_M, (nz - 1) * CELL_M], "voxel_size_m": CELL_M}},
                "materials": [{"label": 1, "name": "gel", "young_pa": YOUNG_PA, "poisson": POISSON, "density_kg_per_m3": DENSITY}],
                "level": 0,
                "damping": {"mass_per_s": 0, "stiffness_s": 0},
                "solver": {"cg_max_iterations": 1000, "cg_tolerance": 1e-5, "preconditioner": preconditioner},
                "fixed": [{"side": {"side": "-x"}}],
            }
        },
        "tools": [{"name": "probe", "shape": {"cylinder": {"radius_m": 0.004, "length_m": 0.08}}}],
    }


def time_cutsim(server, n, preconditioner, steps):
    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as f:
        json.dump(cutsim_scene(n, preconditioner), f)
        path = f.name
    try:
        out = subprocess.run([server, "run", path, "--steps", str(WARM_UP + steps), "--json"], check=True, capture_output=True, text=True)
    finally:
        os.unlink(path)
    report = json.loads(out.stdout)
    counters = report["counters"]
    if counters["solver_cap_hits"]:
        raise SystemExit(f"cutsim {preconditioner}: {counters['solver_cap_hits']} solves hit the cap")
    return {
        "p50_ms": report["step_time_p50_us"] / 1e3,
        "nodes": counters["nodes"],
        "elements": counters["elements"],
        "cg": counters["solver_iterations"] / counters["solves"],
        "residual": counters["solver_max_residual"],
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", required=True)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--out")
    args = parser.parse_args()
    rows = []
    for n in SIZES:
        runs = {"mujoco": [], **{p: [] for p in PRECONDITIONERS}}
        info = {}
        for r in range(args.rounds):
            m = time_mujoco(n, args.steps)
            runs["mujoco"].append(m["p50_ms"])
            info["mujoco"] = m
            for preconditioner in PRECONDITIONERS:
                c = time_cutsim(args.server, n, preconditioner, args.steps)
                runs[preconditioner].append(c["p50_ms"])
                info[preconditioner] = c
            cutsim = ", ".join(f"{p} {runs[p][-1]:.1f} ms" for p in PRECONDITIONERS)
            print(f"{n}: round {r + 1}: MuJoCo {m['p50_ms']:.1f} ms, cutsim {cutsim}", file=sys.stderr, flush=True)
        median = {k: statistics.median(v) for k, v in runs.items()}
        rows.append((n, median, info, runs))
    lines = [
        "# cutsim's level-0 grid against MuJoCo's flex FEM",
        "",
        f"Generated by `tools/fem-comparison/run.sh` ({args.rounds} rounds of {args.steps} timed steps after {WARM_UP} of warm-up, alternating) on "
        f"{cpu_model()}, {os.cpu_count()} logical CPUs ({platform.machine()}), MuJoCo {mujoco.__version__}; do not edit by hand. Step times vary by up to 40 % between hours on this machine; both sides are timed in the same run.",
        "",
        f"A cantilever of {CELL_M * 1e3} mm cells, E = {YOUNG_PA / 1e3:.0f} kPa, ν = {POISSON}, ρ = {DENSITY:.0f} kg/m³, clamped at one end, under gravity, undamped, 1 ms steps, "
        "from rest (it sags through large deformation). MuJoCo: a 3D flexcomp grid (linear tetrahedra) with `integrator=\"discrete\"`. "
        "cutsim: the branched grid at level 0 (trilinear hexahedra, mean dilatation), every step's solve converged to a relative residual of 1e-5 (none hit its cap); "
        "one physics thread, as a session runs.",
        "",
        "| nodes | MuJoCo elements | MuJoCo step p50 | cutsim elements | cutsim Jacobi p50 (CG/step) | cutsim multigrid p50 (CG/step) | cutsim Cholesky p50 (CG/step) | MuJoCo ÷ best cutsim |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    per_round = []
    for n, median, info, runs in rows:
        best = min(PRECONDITIONERS, key=lambda p: median[p])
        cutsim = " | ".join(f"{median[p]:.2f} ms ({info[p]['cg']:.1f})" for p in PRECONDITIONERS)
        lines.append(
            f"| {info['jacobi']['nodes']:,} | {info['mujoco']['elements']:,} | {median['mujoco']:.1f} ms | {info['jacobi']['elements']:,} | "
            f"{cutsim} | {median['mujoco'] / median[best]:.1f}× |"
        )
        ratios = [m / c for m, c in zip(runs["mujoco"], runs[best])]
        per_round += [
            "",
            f"Per round at {info['jacobi']['nodes']:,} nodes, MuJoCo ÷ cutsim {best} in the same round: "
            + ", ".join(f"{r:.1f}×" for r in ratios)
            + f" (median {statistics.median(ratios):.1f}×, range {min(ratios):.1f}–{max(ratios):.1f}×).",
        ]
    text = "\n".join(lines + per_round) + "\n"
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)
        print(f"wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
