"""The sogm-service command as a person meets it: help, missing extras, pipes, refusals."""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sogm_service.apps.cli import build_parser
from sogm_service.client.session import free_tcp_endpoint
from sogm_service.store.directory import DirectoryStore
from tests.conftest import start_server

pytestmark = pytest.mark.integration

MAIN = "from sogm_service.apps.cli import main; raise SystemExit(main(sys.argv[1:]))"
MARKUP = re.compile(r"``|:(mod|func|class|meth|attr):|\*\*\w")  # RST roles, bold; not pose/**


def run_cli(*args: str, without: str | None = None,
            timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    """The command in a child process; ``without``: a module that process sees as not
    installed (None in sys.modules is how Python spells it)."""
    hide = f"sys.modules[{without!r}] = None; " if without else ""
    return subprocess.run([sys.executable, "-c", f"import sys; {hide}{MAIN}", *args],
                          capture_output=True, text=True, timeout=timeout)


def one_line_error(proc: subprocess.CompletedProcess[str]) -> str:
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("sogm-service: "), proc.stderr
    return lines[0]


def command_paths() -> list[list[str]]:
    """Every subcommand of the tree, at every depth."""
    def walk(parser: object, path: list[str]) -> list[list[str]]:
        found = [path] if path else []
        for action in getattr(parser, "_actions", []):
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    found += walk(sub, [*path, name])
        return found
    return walk(build_parser(), [])


def test_the_tree_has_every_command_at_every_depth() -> None:
    paths = {" ".join(p) for p in command_paths()}
    assert {"serve", "router", "query submap", "query stats", "publish-ism", "schemas",
            "tiles ls", "tiles import", "replay carmen", "replay rosbag", "demo", "view",
            "certs init", "export nav2", "import nav2", "eval supercells", "eval matching",
            "bench"} <= paths


def test_help_of_every_subcommand_is_plain_and_says_each_default_once(
        capsys: pytest.CaptureFixture[str]) -> None:
    from sogm_service.apps.cli import main

    for path in [[], *command_paths()]:
        with pytest.raises(SystemExit) as done:
            main([*path, "--help"])
        assert done.value.code == 0, path
        text = capsys.readouterr().out
        assert text.startswith("usage: sogm-service"), path
        assert not MARKUP.search(text), (path, MARKUP.search(text))
        flat = " ".join(text.split())
        for entry in flat.split(" -"):  # one option's help at a time
            assert entry.count("(default") <= 1, (path, entry)


def test_help_in_a_real_process_names_units_and_defaults() -> None:
    proc = run_cli("replay", "carmen", "--help")
    assert proc.returncode == 0, proc.stderr
    flat = " ".join(proc.stdout.split())
    assert "ISM and map cell size (m) (default: 0.05)" in flat
    assert "the log (.gz or plain text)" in flat  # the positional has help too


@pytest.mark.parametrize("argv, missing, words", [
    (["export", "nav2", "--out", "x"], "yaml", "export nav2"),
    (["import", "nav2", "map.yaml", "--layer", "walls"], "yaml", "import nav2"),
    (["serve", "--ros2", "--listen", "tcp/127.0.0.1:0"], "rosbags", "serve --ros2"),
    (["view", "--http", "127.0.0.1:0"], "starlette", "view"),
])
def test_a_missing_extra_is_one_line_naming_it(argv: list[str], missing: str,
                                               words: str) -> None:
    extra = "viewer" if missing == "starlette" else "ros2"
    line = one_line_error(run_cli(*argv, without=missing))
    assert line == (f"sogm-service: {words} needs the {extra} extra: "
                    f"pip install 'sogm-service[{extra}]'")
    # The help does not need the extra.
    helped = run_cli(*[w for w in words.split() if not w.startswith("-")], "--help",
                     without=missing)
    assert helped.returncode == 0 and "usage:" in helped.stdout, helped.stderr


def test_tiles_ls_into_a_closed_pipe_ends_quietly(tmp_path: Path) -> None:
    with DirectoryStore(tmp_path, "lab", 0.1, 4) as store:
        for k in range(900):  # ~100 kB of listing: more than a pipe holds
            store.write(k % 30, k // 30, ["a"], np.zeros((1, 4, 4), np.int16), 1.7e9)
    proc = subprocess.Popen([sys.executable, "-m", "sogm_service", "tiles", "ls",
                             str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    first = proc.stdout.readline()  # what `| head -1` reads, then it leaves
    proc.stdout.close()
    err = proc.stderr.read().decode()
    code = proc.wait(60)
    assert first.startswith(b"map")
    assert code in (0, 141) and "Traceback" not in err and "BrokenPipe" not in err, err


def test_tiles_ls_of_a_missing_folder_is_refused_with_the_prefix(tmp_path: Path) -> None:
    line = one_line_error(run_cli("tiles", "ls", str(tmp_path / "missing")))
    assert line == f"sogm-service: tiles ls: {tmp_path / 'missing'} is not a directory"


def test_a_usage_mistake_is_one_line() -> None:
    line = one_line_error(run_cli("query", "submap", "--width", "wide"))
    assert "--width" in line and "'sogm-service query submap -h'" in line


def test_a_query_for_a_map_no_server_has_says_so(tmp_path: Path) -> None:
    srv = start_server(tmp_path)
    try:
        line = one_line_error(run_cli("query", "info", "--map", "nosuchmap", "--connect",
                                      srv.endpoint, "--timeout", "2"))
    finally:
        srv.terminate()
    assert f"no server answers for map 'nosuchmap' at {srv.endpoint}" in line
    assert "sogm/nosuchmap/@server/*" in line and "maps served there: default" in line


def test_no_server_at_all_is_still_a_connect_error() -> None:
    endpoint = free_tcp_endpoint()
    line = one_line_error(run_cli("query", "info", "--connect", endpoint,
                                  "--timeout", "2"))
    assert f"no sogm-service reachable at {endpoint}" in line


def test_the_console_script_is_the_same_tree() -> None:
    script = Path(sys.executable).with_name("sogm-service")
    if not script.exists():
        pytest.skip("the console script is not installed next to this interpreter")
    proc = subprocess.run([str(script), "tiles", "--help"], capture_output=True, text=True,
                          timeout=60, env={**os.environ})
    assert proc.returncode == 0 and "usage: sogm-service tiles" in proc.stdout
