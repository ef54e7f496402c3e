"""Every command that reads what a user gives, over the hostile-input corpus (``hostile_corpus.py``): no
traceback, no input changed, memory and time bounded, every invalid case refused with a message that
names the file or the field; and the runner's checks, on commands made to fail each of them."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

import hostile_corpus as corpus


def test_every_reading_command_over_the_hostile_corpus(tmp_path):
    out = tmp_path / "rows.json"
    env = {**os.environ, "PYTHONPATH": str(corpus.ROOT), "WAST3D_TREE": str(corpus.ROOT)}
    r = subprocess.run([sys.executable, corpus.__file__, "--runner", str(out)], env=env, capture_output=True, text=True,
                       timeout=1200)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = json.loads(out.read_text())
    assert len(rows) == len(corpus.cases()) >= 200
    assert sum(not r["valid"] for r in rows) >= 150  # mostly cases that must be refused
    bad = [f"{r['case']}: {r['verdict']} (exit {r['rc']}): {r['message']}" for r in rows if r["verdict"] != "ok"]
    assert not bad, "\n".join(bad)


@pytest.fixture
def faults(monkeypatch):
    """``wast3d corpus-fault-KIND PATH`` commands that break one rule each."""
    from wast3d import cli

    def make(kind):
        def cmd(sub):
            sub.add_argument("path")

            def run(a):
                if kind == "traceback":
                    raise RuntimeError("a fault")
                if kind == "change":
                    with open(a.path, "ab") as f:
                        f.write(b"x")
                if kind == "memory":
                    big = np.ones(3 << 27)  # 3 GiB, touched: past MEMORY_LIMIT
                    import time

                    time.sleep(0.2)
                    del big
                if kind == "silent":
                    from wast3d.ply import PlyError

                    raise PlyError("something is wrong")  # a one-line error that names nothing
                return 0

            return run

        return cmd

    for kind in ("traceback", "change", "memory", "silent", "ok"):
        monkeypatch.setitem(cli.COMMANDS, f"corpus-fault-{kind}", (make(kind), kind))


def test_the_runner_catches_each_kind_of_failure(tmp_path, faults):
    (tmp_path / "inp").mkdir()
    (tmp_path / "out").mkdir()
    shutil.copy(corpus.ROOT / "README.md", tmp_path / "inp" / "f.txt")
    case = lambda kind, valid=False: corpus.Case(kind, (f"corpus-fault-{kind}", "{d}/inp/f.txt"), valid, "f.txt")  # noqa: E731
    verdict = lambda c: corpus.run_case(c, tmp_path, corpus.ROOT)["verdict"]  # noqa: E731
    assert verdict(case("traceback")) == "traceback"
    assert verdict(case("change")).startswith("changed f.txt")
    assert verdict(case("memory")).startswith("memory grew")
    assert verdict(case("ok")) == "exit 0 on an invalid case"
    assert verdict(case("silent")) == "message does not name 'f.txt'"
    assert verdict(case("ok", valid=True)) == "ok"
    assert verdict(case("silent", valid=True)) == "exit 2 on a valid case"
