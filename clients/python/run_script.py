#!/usr/bin/env python3
"""Runs a cut script on cutsim-server from Python and checks its report.

The bot a CI job would write, in one short script: create a lockstep session on the
script's scene, run the script over gRPC (progress events stream while it runs, the
report comes last), check the expectations, close the session. The stubs come from
proto/cutsim.proto (run ./setup.sh once).

    CUTSIM_OPERATOR_TOKEN=… .venv/bin/python run_script.py ../cut-bot/examples/skin-patch-straight.json --server 127.0.0.1:50051

Creating a session needs an operator token (--operator-token, or $CUTSIM_OPERATOR_TOKEN):
the server prints one at start when its config names none.
"""

import argparse
import json
import os
import sys
from pathlib import Path

import grpc

sys.path.insert(0, str(Path(__file__).parent / "generated"))
import cutsim_pb2  # noqa: E402  (generated)
import cutsim_pb2_grpc  # noqa: E402  (generated)


def run(server: str, script_path: str, operator_token: str) -> cutsim_pb2.ScriptReport:
    """Runs the script on a fresh lockstep session and returns the report."""
    script = Path(script_path).read_text()
    scene = json.loads(script)["scene"]
    with grpc.insecure_channel(server) as channel:
        sessions = cutsim_pb2_grpc.SessionsStub(channel)
        created = sessions.CreateSession(
            cutsim_pb2.CreateSessionRequest(scene_name=scene, mode=cutsim_pb2.SESSION_MODE_LOCKSTEP, label="python example"),
            metadata=[("cutsim-token", operator_token)],
        )
        token = [("cutsim-token", created.control_token)]
        try:
            report = None
            events = cutsim_pb2_grpc.ScriptsStub(channel).RunScript(
                cutsim_pb2.RunScriptRequest(session_id=created.session.id, script_json=script), metadata=token
            )
            for event in events:
                if event.HasField("progress"):
                    p = event.progress
                    print(f"step {p.step}/{p.total_steps}, cuts {p.cuts}", file=sys.stderr)
                else:
                    report = event.report
            return report
        finally:
            sessions.CloseSession(cutsim_pb2.CloseSessionRequest(session_id=created.session.id), metadata=token)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("script", help="a cut script (docs/cut-script.md)")
    parser.add_argument("--server", default="127.0.0.1:50051", help="host:port of cutsim-server's gRPC")
    parser.add_argument("--operator-token", default=os.environ.get("CUTSIM_OPERATOR_TOKEN", ""), help="creating a session needs one (default: $CUTSIM_OPERATOR_TOKEN)")
    args = parser.parse_args()
    try:
        report = run(args.server, args.script, args.operator_token)
    except grpc.RpcError as e:
        print(f"error: {e.code().name}: {e.details()}", file=sys.stderr)
        return 2
    print(f"{report.scene}: {report.steps} steps, {report.cuts} cut(s), incision {report.incision_length_m * 1000:.1f} mm, state_hash {report.state_hash}")
    for t in report.tools:
        grasping = f", grasping {t.grasping_s:.3f} s, pinching at most {t.max_jaws_force_n:.2f} N" if t.grasping_s > 0 else ""
        print(f"tool {t.name}: largest force {t.max_force_n:.2f} N{grasping}")
    for f in report.fallbacks:
        print(f"fallback at step {f.step}: {f.reason}")
    for e in report.expectations:
        print(f"{'PASS' if e.passed else 'FAIL'} {e.name}: expected {e.expected}, got {e.actual}")
    return 0 if report.passed else 1


if __name__ == "__main__":
    sys.exit(main())
