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


class RunScriptExample(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.recordings = tempfile.TemporaryDirectory()
        cls.server = subprocess.Popen(
            [SERVER, "serve", "--no-session", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0", "--recordings-dir", cls.recordings.name],
            stdout=subprocess.PIPE, text=True, env={**os.environ, "RUST_LOG": "warn"},
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
        return subprocess.run([sys.executable, str(HERE / "run_script.py"), str(script), "--server", self.address], capture_output=True, text=True, timeout=120)

    def test_example_passes(self):
        result = self.run_example(REPO / "clients" / "cut-bot" / "examples" / "skin-patch-straight.json")
        self.assertEqual(result.returncode, 0, result.stdout + result.stderr)
        self.assertIn("PASS cuts: expected = 1, got 1", result.stdout)
        self.assertRegex(result.stdout, r"state_hash [0-9a-f]{16}")

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


if __name__ == "__main__":
    unittest.main()
