#!/usr/bin/env python3
"""Writes the cut scripts of the CT skin scene (clients/cut-bot/examples/skin-real-*.json).

The CT skin is curved (the anterior abdomen bulges towards -y by up to 9 mm across the
patch), so a scalpel held at one height would dip in and out of it. Each script here
holds the blade as a surgeon does: its tip a fixed depth under the skin beneath it, its
shaft out through the skin along the outward normal (-y), and its edge (the tool's +x)
turned along the way it is drawn, so that the edge leads and the skin's fracture
toughness sets the force. The skin's height under the path is read from the scene's own
mesh (in the shared data directory, $CUTSIM_DATA_DIR or ../shared/data).

It also writes the straight cuts across the whole patch every 1.5 mm from z = -12 to
+12 mm that server/sim/tests/real_skin_cut.rs runs through the node-matching
reconstruction (server/sim/tests/data/skin-real-across.json: one script per line).

Usage: python3 scripts/skin-real-examples.py           (rewrites the five files)
       python3 scripts/skin-real-examples.py --check   (fails, naming them, where the
                                                          files differ from what it writes;
                                                          the test command runs it)
"""

import json
import math
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXAMPLES = os.path.join(ROOT, "clients", "cut-bot", "examples")
ACROSS = os.path.join(ROOT, "server", "sim", "tests", "data", "skin-real-across.json")
# The cuts across the patch: z from ACROSS_FROM_M every ACROSS_EVERY_M, ACROSS_CUTS of them.
ACROSS_FROM_M, ACROSS_EVERY_M, ACROSS_CUTS = -0.012, 0.0015, 17
# The blade's tip under the skin, m: the default scene's scripts cut with it 5 mm below.
TIP_DEPTH_M = 0.005
# Where the blade is lifted to after the cut: its tip this far outside the skin, m.
LIFT_M = 0.02
# Keyframes at least this close along the path, m, so that the tip follows the skin.
KEYFRAME_SPACING_M = 0.004


def load_skin():
    scene = json.load(open(os.path.join(ROOT, "server", "scenes", "skin-real.json")))
    obj = scene["model"]["msm"]["geometry"]["obj"]
    data = os.environ.get("CUTSIM_DATA_DIR") or os.path.join(ROOT, "..", "shared", "data")
    path = os.path.join(data, obj["path"].removeprefix("data:"))
    if not os.path.exists(path):
        sys.exit(f"skin-real-examples: the CT skin mesh is not at {path}: set CUTSIM_DATA_DIR to the shared data directory")
    scale, offset = obj["scale_m_per_unit"], obj["offset_m"]
    vertices, triangles = [], []
    for line in open(path):
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            vertices.append([float(parts[i + 1]) * scale + offset[i] for i in range(3)])
        elif parts[0] == "f":
            triangles.append([int(p.split("/")[0]) - 1 for p in parts[1:4]])
    return scene, vertices, triangles


def surface_y(vertices, triangles, x, z):
    """The skin's height (y) under (x, z): the mesh's crossing of the line along y there,
    or, off the mesh, the height at its nearest vertex in the xz plane."""
    for tri in triangles:
        a, b, c = (vertices[i] for i in tri)
        # Barycentric coordinates of (x, z) in the triangle projected on xz.
        det = (b[0] - a[0]) * (c[2] - a[2]) - (c[0] - a[0]) * (b[2] - a[2])
        if abs(det) < 1e-15:
            continue
        u = ((x - a[0]) * (c[2] - a[2]) - (c[0] - a[0]) * (z - a[2])) / det
        v = ((b[0] - a[0]) * (z - a[2]) - (x - a[0]) * (b[2] - a[2])) / det
        if u >= -1e-9 and v >= -1e-9 and u + v <= 1 + 1e-9:
            return a[1] + u * (b[1] - a[1]) + v * (c[1] - a[1])
    nearest = min(vertices, key=lambda p: (p[0] - x) ** 2 + (p[2] - z) ** 2)
    return nearest[1]


def blade_orientation(tangent_xz):
    """The unit quaternion (w, x, y, z) turning the tool's +z to the skin's outward -y
    and its edge (+x) along `tangent_xz`, a direction in the xz plane: a quarter turn
    about x (+z to -y, +x kept), then a turn by phi about y (+x to the tangent, -y kept),
    whose product is sqrt(1/2) (cos(phi/2), cos(phi/2), sin(phi/2), -sin(phi/2))."""
    phi = math.atan2(-tangent_xz[1], tangent_xz[0])
    c, s = math.cos(phi / 2) / math.sqrt(2), math.sin(phi / 2) / math.sqrt(2)
    return [round(q, 9) + 0.0 for q in (c, c, s, -s)]  # + 0.0: no "-0.0" in the files


def cut_keyframes(skin, path_xz, start_step, end_step):
    """Keyframes drawing the blade along the polyline `path_xz` (points (x, z)) from
    `start_step` to `end_step` at an even speed, its tip TIP_DEPTH_M under the skin and
    its edge along the way; then lifted out along its axis over 50 steps. The blade is
    under the skin from the first step: it punctures the skin where it stands, as the
    skin-patch scripts' blade does."""
    vertices, triangles = skin
    # Resample the polyline so that the tip follows the skin between its points.
    points = [path_xz[0]]
    for a, b in zip(path_xz, path_xz[1:]):
        pieces = max(1, math.ceil(math.dist(a, b) / KEYFRAME_SPACING_M))
        points += [(a[0] + (b[0] - a[0]) * k / pieces, a[1] + (b[1] - a[1]) * k / pieces) for k in range(1, pieces + 1)]
    lengths = [0.0]
    for a, b in zip(points, points[1:]):
        lengths.append(lengths[-1] + math.dist(a, b))
    keyframes = []
    for i, (x, z) in enumerate(points):
        before, after = points[max(i - 1, 0)], points[min(i + 1, len(points) - 1)]
        turn = blade_orientation((after[0] - before[0], after[1] - before[1]))
        step = start_step + round((end_step - start_step) * lengths[i] / lengths[-1])
        y = surface_y(vertices, triangles, x, z) + TIP_DEPTH_M
        keyframes.append({"step": step, "position_m": [round(x, 6), round(y, 6), round(z, 6)], "orientation_wxyz": turn, "cut": True})
    keyframes[-1]["cut"] = False
    last = keyframes[-1]
    out = [last["position_m"][0], last["position_m"][1] - TIP_DEPTH_M - LIFT_M, last["position_m"][2]]
    keyframes.append({"step": end_step + 50, "position_m": [round(c, 6) for c in out], "orientation_wxyz": last["orientation_wxyz"], "active": False})
    return keyframes


def script_text(script):
    """An example script as the files hold it: indented JSON and a final newline."""
    return json.dumps(script, indent=2) + "\n"


def generated_files():
    """Every file this script writes, as {path: text}, in the order it writes them."""
    scene, vertices, triangles = load_skin()
    skin = (vertices, triangles)
    task = [(p[0], p[2]) for p in scene["task"]["incision"]["points_m"]]
    existing = lambda name: json.load(open(os.path.join(EXAMPLES, name)))
    files = {}

    # Each script keeps its expectations and length; only the blade's way changes.
    # (script, the blade's way, its first and last step drawing)
    for name, path, start, end in [
        ("skin-real-curved.json", task, 0, 600),
        ("skin-real-straight.json", [(-0.03, 0.02), (0.03, -0.01)], 0, 400),
        # From off the skin at one side to off it at the other: in from the side, no
        # puncture.
        ("skin-real-separate.json", [(-0.065, 0.0), (0.065, 0.0)], 0, 800),
        # The bad attempt at the half circle: straight across from its one end to the other.
        ("skin-real-task-bad.json", [task[0], task[-1]], 0, 500),
    ]:
        script = existing(name)
        script["tools"] = [{"tool": "scalpel", "keyframes": cut_keyframes(skin, path, start, end)}]
        files[os.path.join(EXAMPLES, name)] = script_text(script)

    # The separating cut, drawn across the patch at each z: one script per line. (Its
    # expectations are the separate script's as generated above.)
    separate = json.loads(files[os.path.join(EXAMPLES, "skin-real-separate.json")])
    across = []
    for k in range(ACROSS_CUTS):
        z = round(ACROSS_FROM_M + k * ACROSS_EVERY_M, 6)
        script = dict(separate, tools=[{"tool": "scalpel", "keyframes": cut_keyframes(skin, [(-0.065, z), (0.065, z)], 0, 800)}])
        across.append(json.dumps(script, separators=(",", ":")))
    files[ACROSS] = "[\n" + ",\n".join(across) + "\n]\n"
    return files


def main():
    check = sys.argv[1:] == ["--check"]
    if sys.argv[1:] and not check:
        sys.exit(f"skin-real-examples: unknown arguments {sys.argv[1:]}; usage: skin-real-examples.py [--check]")
    files = generated_files()
    if check:
        stale = [path for path, text in files.items() if not os.path.exists(path) or open(path).read() != text]
        for path in stale:
            print(f"skin-real-examples: {os.path.relpath(path, ROOT)} is not what this script writes (edited by hand, or the script or the CT skin changed): run python3 scripts/skin-real-examples.py and commit the result", file=sys.stderr)
        if stale:
            sys.exit(1)
        print(f"skin-real-examples: the {len(files)} files are what this script writes")
        return
    for path, text in files.items():
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            f.write(text)
        print(f"wrote {os.path.relpath(path, ROOT)}")


if __name__ == "__main__":
    main()
