"""Every command the README shows is one a user can type and it works.

Each line of the README's ```sh blocks is run, in the README's order, as a user in the repository folder would:
in a scratch folder holding a copy of the repository's pipeline.yaml, where `workspace/` is the default workspace.
Only the sizes shrink: `fullview synth` renders 3 views at 512 px instead of the README's, every pipeline command
gets the tiny test settings (conftest's TINY_OVERRIDES and a small dense stage) appended as `--set`, and the user's
own dataset (`my_capture`) is a link to the synthetic scene the README's first run renders, so the pipeline runs
once (a link resolves to the same dataset name, hence the same results). `make` lines are checked with `make -n`
(the target exists and its recipe expands), `source .venv/bin/activate` against the Makefile and pyproject. A line
of any other shape fails the test: the README shows no command that is not run here.

Besides: every inline `fullview …` in the README's text parses with the real command line, every inline `make …`
names a target, and every file the README's "What comes out" table names exists after the commands ran.
"""

from __future__ import annotations

import os
import re
import selectors
import shlex
import shutil
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

import fullview
from fullview.cli import build_parser, main

from tests.conftest import TINY_OVERRIDES

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
TEXT = README.read_text()
PIPELINE_COMMANDS = {"run", "status", "eval", "export", "view", "report"}
SMALL = [*TINY_OVERRIDES, "densify.working_width=512", "densify.rect_height=256", "densify.min_pair_inliers=30"]
SYNTH_SIZE = {"--views": "3", "--width": "512"}
USER_DATASET = "my_capture"
FIRST_RUN_DATASET = "workspace/datasets/synth6"


def sh_lines(text: str) -> list[str]:
    """The command lines of the ```sh blocks, comments dropped."""
    lines = []
    for block in re.findall(r"^```sh\n(.*?)^```", text, re.S | re.M):
        for line in block.splitlines():
            line = line.split(" #")[0].strip() if not line.lstrip().startswith("#") else ""
            if line:
                lines.append(line)
    return lines


def inline_spans(text: str, program: str) -> list[str]:
    """Inline code spans that start with `program ` outside the code blocks, without placeholders (…)."""
    prose = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return [s for s in re.findall(r"`([^`\n]+)`", prose) if s.startswith(program + " ") and "…" not in s]


COMMANDS = sh_lines(TEXT)


def test_the_readme_shows_commands_and_stays_a_manual():
    assert any(c.startswith("fullview run") for c in COMMANDS) and any(c.startswith("make") for c in COMMANDS)
    assert len(TEXT.splitlines()) <= 300


def _fullview_argv(line: str) -> list[str] | None:
    words = shlex.split(line)
    for prefix in (["fullview"], [".venv/bin/fullview"], ["python", "-m", "fullview"]):
        if words[:len(prefix)] == prefix:
            return words[len(prefix):]
    return None


def _shrunk(argv: list[str]) -> list[str]:
    """The README's arguments with the tiny sizes and settings of the tests."""
    argv = list(argv)
    if argv and argv[0] == "synth":
        for flag, value in SYNTH_SIZE.items():
            if flag in argv:
                argv[argv.index(flag) + 1] = value
            else:
                argv += [flag, value]
    if argv and argv[0] in PIPELINE_COMMANDS:
        argv += [a for s in SMALL for a in ("--set", s)]
    return argv


def _view(argv: list[str], cwd: Path) -> tuple[int, str]:
    """`fullview view` in a child process: wait for its address, fetch the page, stop the child."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(fullview.__file__).resolve().parents[1]),
                                                       os.environ.get("PYTHONPATH", "")]))
    if "--no-browser" not in argv:
        argv = [*argv, "--no-browser"]  # a test opens no browser; the README's view commands are otherwise run as shown
    proc = subprocess.Popen([sys.executable, "-m", "fullview", *argv], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    out = ""
    try:
        sel = selectors.DefaultSelector()
        sel.register(proc.stdout, selectors.EVENT_READ)
        while "http://" not in out and proc.poll() is None and sel.select(timeout=120):
            out += proc.stdout.readline()
        url = re.search(r"http://127\.0\.0\.1:\d+/?", out)
        if url is None:
            return 1, out
        with urllib.request.urlopen(url.group(0), timeout=60) as response:
            page = response.read().decode()
        return (0 if response.status == 200 and "<html" in page.lower() else 1), out
    finally:
        proc.terminate()
        proc.wait(timeout=60)


def _run_line(line: str, cwd: Path, capsys) -> tuple[int, str]:
    words = shlex.split(line)
    if words == ["source", ".venv/bin/activate"]:
        makefile, pyproject = (ROOT / "Makefile").read_text(), (ROOT / "pyproject.toml").read_text()
        ok = re.search(r"^VENV\s*:=\s*\.venv$", makefile, re.M) and 'fullview = "fullview.cli:main"' in pyproject
        return (0 if ok else 1), "the venv make setup creates, with the fullview command"
    if words[0] == "make":
        proc = subprocess.run(["make", "-n", *words[1:]], cwd=ROOT, capture_output=True, text=True)
        return proc.returncode, proc.stdout + proc.stderr
    argv = _fullview_argv(line)
    if argv is None:
        return 1, "not a command this test knows how to run: keep the README to fullview and make commands"
    argv = _shrunk(argv)
    if argv and argv[0] == "view":
        return _view(argv, cwd)
    try:
        code = main(argv)
    except SystemExit as e:  # --help
        code = e.code
    out = capsys.readouterr()
    return code, out.out + out.err


@pytest.fixture(scope="module")
def readme_session(tmp_path_factory):
    """The folder the README's commands ran in and their results, in order (lazily, as the tests ask)."""
    cwd = tmp_path_factory.mktemp("readme")
    shutil.copy(ROOT / "pipeline.yaml", cwd / "pipeline.yaml")
    (cwd / USER_DATASET).symlink_to(cwd / FIRST_RUN_DATASET, target_is_directory=True)
    return {"cwd": cwd, "results": []}


@pytest.fixture
def ran(readme_session, capsys, monkeypatch):
    """Run the README's commands up to index i (each once per session) and return its exit code and output."""
    monkeypatch.chdir(readme_session["cwd"])
    results = readme_session["results"]

    def upto(i: int) -> tuple[int, str]:
        while len(results) <= i:
            results.append(_run_line(COMMANDS[len(results)], readme_session["cwd"], capsys))
        return results[i]
    return upto


@pytest.mark.parametrize("index", range(len(COMMANDS)), ids=[c[:60] for c in COMMANDS])
def test_each_readme_command_runs(ran, index):
    code, output = ran(index)
    assert code == 0, f"README command {COMMANDS[index]!r} exited {code}:\n{output[-3000:]}"


def test_the_outputs_the_readme_names_exist(ran, readme_session):
    ran(len(COMMANDS) - 1)
    section = TEXT.split("## What comes out", 1)[1].split("\n## ", 1)[0]
    names = re.findall(r"^\| `([^`]+)` \|", section, re.M)
    assert len(names) >= 5, "the README's outputs table lost its rows"
    results = readme_session["cwd"] / "workspace" / "synth6"
    for name in names:
        pattern = re.sub(r"<[^>]+>", "*", name).rstrip("/")
        assert list(results.glob(pattern)), f"README names {name}, but the commands left no {results / pattern}"


@pytest.mark.parametrize("span", inline_spans(TEXT, "fullview"))
def test_each_inline_fullview_command_parses(span, capsys):
    words = shlex.split(span)[1:]
    if len(words) == 1:  # a command named in the text (`fullview eval`): it exists
        words.append("--help")
    try:
        build_parser().parse_args(words)
    except SystemExit as e:
        assert e.code == 0, f"README's `{span}` is not a valid command: {capsys.readouterr().err}"


@pytest.mark.parametrize("span", inline_spans(TEXT, "make"))
def test_each_inline_make_target_exists(span):
    proc = subprocess.run(["make", "-n", *shlex.split(span)[1:]], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, f"README's `{span}`: {proc.stderr}"
