"""Tests the Python example against a real cutsim-server (started here)."""

import os
import re
import subprocess
import sys
import tempfile
import unittest
from pathlib import Path

HERE = Path(__file__).parent
REPO = HERE.parent.parent
SERVER = os.environ.get("CUTSIM_SERVER_BIN", str(REPO / "target" / "debug" / "cutsim-server"))
OPERATOR = "python-test-operator-0123456789abcdef"


class RunScriptExample(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.recordings = tempfile.TemporaryDirectory()
        cls.server = subprocess.Popen(
            [SERVER, "serve", "--no-session", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0", "--recordings-dir", cls.recordings.name],
            stdout=subprocess.PIPE, text=True, env={**os.environ, "RUST_LOG": "warn", "CUTSIM_OPERATOR_TOKEN": OPERATOR},
        )
        for line in cls.server.stdout:
            found = re.match(r"grpc listening on (\S+)", line)
            if found:
                cls.address = found.group(1)
                break
        else:
            raise RuntimeError("cutsim-server did not start")

    @classmethod
    def tearDownClass(cls):
        cls.server.kill()
        cls.server.wait()
        cls.recordings.cleanup()

    def run_example(self, script):
        env = {**os.environ, "CUTSIM_OPERATOR_TOKEN": OPERATOR}
        return subprocess.run([sys.executable, str(HERE / "run_script.py"), str(script), "--server", self.address], capture_output=True, text=True, timeout=120, env=env)

    def test_example_passes(self):
        result = self.run_example(REPO / "clients" / "cut-bot" / "examples" / "skin-patch-straight.json")
        self.assertEqual(result.returncode, 0, result.stdout + result.stderr)
        self.assertIn("PASS cuts: expected = 1, got 1", result.stdout)
        self.assertRegex(result.stdout, r"state_hash [0-9a-f]{16}")
        # Each tool's largest force (the scalpel cuts; the forceps stay away).
        self.assertRegex(result.stdout, r"tool scalpel: largest force [1-9][0-9.]* N")
        self.assertIn("tool forceps: largest force 0.00 N", result.stdout)

    def test_forceps_report_their_grasp_and_pinch(self):
        result = self.run_example(REPO / "clients" / "cut-bot" / "examples" / "skin-patch-retract.json")
        self.assertEqual(result.returncode, 0, result.stdout + result.stderr)
        self.assertRegex(result.stdout, r"tool forceps: largest force [0-9.]+ N, grasping 0\.[0-9]+ s, pinching at most 3\.00 N")
        self.assertIn("PASS tools.forceps.max_jaws_force_n", result.stdout)

    def test_failed_expectation_exits_1(self):
        text = (REPO / "clients" / "cut-bot" / "examples" / "skin-patch-straight.json").read_text()
        with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as f:
            f.write(text.replace('"pieces": { "equals": 1 }', '"pieces": { "equals": 3 }'))
        result = self.run_example(f.name)
        os.unlink(f.name)
        self.assertEqual(result.returncode, 1, result.stdout + result.stderr)
        self.assertIn("FAIL pieces: expected = 3, got 1", result.stdout)

    def test_unknown_scene_is_a_clear_error(self):
        with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as f:
            f.write('{"scene": "no-such-scene", "tools": []}')
        result = self.run_example(f.name)
        os.unlink(f.name)
        self.assertEqual(result.returncode, 2)
        self.assertIn("INVALID_ARGUMENT", result.stderr)
        self.assertIn("no-such-scene", result.stderr)

    def test_without_an_operator_token_creating_is_refused(self):
        env = {k: v for k, v in os.environ.items() if k != "CUTSIM_OPERATOR_TOKEN"}
        script = REPO / "clients" / "cut-bot" / "examples" / "skin-patch-straight.json"
        result = subprocess.run([sys.executable, str(HERE / "run_script.py"), str(script), "--server", self.address], capture_output=True, text=True, timeout=120, env=env)
        self.assertEqual(result.returncode, 2)
        self.assertIn("UNAUTHENTICATED", result.stderr)

    def test_grpcio_reflection_lists_the_services(self):
        """grpcio's reflection client speaks grpc.reflection.v1alpha, as Python tooling does."""
        import grpc
        from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

        with grpc.insecure_channel(self.address) as channel:
            database = ProtoReflectionDescriptorDatabase(channel)
            services = set(database.get_services())
            self.assertTrue({"cutsim.v1.Sessions", "cutsim.v1.Haptics", "cutsim.v1.Scripts", "grpc.health.v1.Health"} <= services, services)
            sessions = database.FindFileContainingSymbol("cutsim.v1.Sessions")
            self.assertEqual(sessions.package, "cutsim.v1")

    def test_errors_carry_google_rpc_details(self):
        """A bad scene comes back with a BadRequest naming the JSON path of the bad value."""
        import grpc
        from google.rpc import error_details_pb2, status_pb2

        sys.path.insert(0, str(HERE / "generated"))
        import cutsim_pb2
        import cutsim_pb2_grpc

        with grpc.insecure_channel(self.address) as channel:
            scene = (REPO / "server" / "scenes" / "skin-patch.json").read_text().replace('"young_pa": 100000', '"young_pa": -5')
            with self.assertRaises(grpc.RpcError) as raised:
                cutsim_pb2_grpc.SessionsStub(channel).CreateSession(cutsim_pb2.CreateSessionRequest(scene_json=scene), metadata=[("cutsim-token", OPERATOR)])
            error = raised.exception
            self.assertEqual(error.code(), grpc.StatusCode.INVALID_ARGUMENT)
            details = dict(error.trailing_metadata())["grpc-status-details-bin"]
            status = status_pb2.Status.FromString(details)
            bad_request = error_details_pb2.BadRequest()
            self.assertTrue(status.details[0].Unpack(bad_request))
            self.assertEqual(bad_request.field_violations[0].field, "scene_json.model.msm.material.young_pa")


if __name__ == "__main__":
    unittest.main()
