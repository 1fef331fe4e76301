"""Every command line the documentation quotes for an experiment (README.md, experiments/*.md and the experiments'
own docstrings: ``python experiments/X.py ...``, ``experiments/X.py --...``, ``X.py --...``) parses against that
experiment's parser as it is today, with every option written out in full; and every option a quoted ``svs-depth``
command gives is one its command has. A reader reproducing a table runs these lines: a renamed option left in the
text would end in "unrecognized arguments", or, where the new name only extends the old (``--contrast`` for
``--contrasts``), be taken silently by argparse's prefix matching. Documents keep what was run; a renamed option
gets a note "(since renamed: --new)" beside the old line, and the line itself the new name (an audit)."""

from __future__ import annotations

import itertools
import os
import re
import shlex

import pytest
from conftest import REPO_ROOT, find_shared_data

SCRIPTS = {path.stem for path in (REPO_ROOT / "experiments").glob("*.py")}
DOCS = [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "experiments").glob("*.md")),
        *sorted((REPO_ROOT / "experiments").glob("*.py"))]
START = re.compile(r"python3? experiments/(?P<run>\w+)\.py(?=\s|$)|(?:experiments/)?(?P<named>\w+)\.py(?= -)"
                   r"|(?:svs-depth|python -m svs_torch\.cli)(?=\s|$)")
WEIGHTS = str(REPO_ROOT / "svs_torch" / "segmentation" / "weights")
# What a placeholder of the documents (N, FILE, D, ...) stands for, by the option it follows.
VALUES = {"--noise-seed": "0", "--limit": "1", "--digit": "4", "--camera-frames": "4", "--loose-rig-digit": "4",
          "--repeats": "1", "--contrast": "0.5", "--brightness": "1.4", "--steps": "1", "--weights":
          WEIGHTS + "/obstacle_net.pt", "--data": str(find_shared_data() or "."), "--pairs": "pairs.txt", "--seed": "1"}
OUTPUTS = ("--json", "--markdown", "--out")


def quoted_commands() -> list[tuple[str, str]]:
    """``(where, command)`` of every quoted command line: inline spans (`...` in markdown, ``...`` in docstrings),
    then the lines of indented or fenced blocks, a trailing backslash or a deeper indent continuing a line."""
    found = []
    for doc in DOCS:
        text, where = doc.read_text(), doc.relative_to(REPO_ROOT)
        span = re.compile(r"``(.+?)``", re.S) if doc.suffix == ".py" else re.compile(r"(?<!`)`([^`]+?)`(?!`)", re.S)
        for match in span.finditer(text):
            command = " ".join(match.group(1).split())
            if START.match(command):
                found.append((f"{where}:{text.count(chr(10), 0, match.start()) + 1}", command))
        lines = span.sub(lambda m: re.sub(r"[^\n]", " ", m.group(0)), text).split("\n")
        for number, line in enumerate(lines):
            block = line.startswith("    ") or doc.suffix == ".md" and line == line.strip()  # (indented, fenced)
            if not block or not START.match(line.strip()):
                continue
            command, indent, end = line.strip(), len(line) - len(line.lstrip()), number + 1
            while end < len(lines) and (command.endswith("\\") or lines[end].strip() and not START.match(
                    lines[end].strip()) and len(lines[end]) - len(lines[end].lstrip()) > indent
                    and not lines[end].strip().startswith('"""')):
                command, end = command.rstrip("\\").rstrip() + " " + lines[end].strip(), end + 1
            found.append((f"{where}:{number + 1}", re.sub(r"\s+#\s.*$", "", command)))
    return found


def variants(arguments: str) -> list[list[str]]:
    """The command lines a usage template stands for: ``[X]`` given, each of ``[A | B]`` and ``a|b``, ``[--set ...]``
    and a pipe or redirection left out."""
    arguments = re.sub(r"\s+(\|\s+(tail|head)|>)\s.*$", "", arguments)
    arguments = re.sub(r",\s+", ",", re.sub(r"\[--set [^\]]*\.\.\.\]|\[:PATH\]|\[,N\.\.\.\]", "", arguments))
    parts = [[alt.strip() for alt in part[1:-1].split(" | ")] if part.startswith("[") else [part]
             for part in re.split(r"(\[[^\[\]]*\])", arguments)]
    out = []
    for text in (" ".join(choice) for choice in itertools.product(*parts)):
        tokens = shlex.split(text)
        alternatives = [token.split("|") if "|" in token and not token.startswith("-") else [token] for token in tokens]
        out += [list(combination) for combination in itertools.product(*alternatives)]
    return out


def concrete(tokens: list[str], folder: str) -> list[str]:
    """``tokens`` with each placeholder (N, FILE, KEY=R, nearness:FILE) a value and each report in ``folder``."""
    argv = []
    for previous, token in zip(["", *tokens], tokens):
        if previous in OUTPUTS:
            token = os.path.join(folder, "report" + os.path.splitext(token)[1])
        elif re.fullmatch(r"[A-Z]+(\.\.\.)?", token):
            assert previous in VALUES, f"no value for the placeholder {token} after {previous!r}: add one to VALUES"
            token = VALUES[previous]
        token = re.sub(r"=[A-Z]$", "=1", token.replace("nearness:FILE", f"nearness:{WEIGHTS}/nearness_net.pt"))
        argv.append(token)
    return argv


#: What is wrong with each ``(script, argv)`` of ``sys.argv[1]`` (JSON; "svs-depth" for the command line): nothing
#: when it parses with every option written out in full. Run in a fresh process by conftest.experiment_calls.
RUNNER = r"""
import argparse, contextlib, io, json, sys
sys.path.insert(0, "experiments")
original = argparse.ArgumentParser.parse_args

class Parsed(Exception):
    pass

def parse_args(self, args=None, namespace=None):
    original(self, args, namespace)
    raise Parsed(self)

argparse.ArgumentParser.parse_args = parse_args
from svs_torch.cli import build_parser
commands = build_parser().commands()
results = []
for script, argv in json.loads(sys.argv[1]):
    err = io.StringIO()
    if script == "svs-depth":  # (a quoted svs-depth command may be a part of one: its command and option names)
        command = next((token for token in argv if not token.startswith("-")), None)
        parser = commands.get(command, build_parser())
        results.append([arg.split("=")[0] for arg in argv if arg.startswith("--") and arg.split("=")[0] not in
                        (*parser._option_string_actions, "--help")] + ([] if command in (None, *commands) else
                        [f"no command {command}"]))
        continue
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            module = __import__(script)
            sys.argv = [script + ".py", *argv]
            module.main(argv) if "argv" in module.main.__code__.co_varnames else module.main()
        results.append(["ran past its parse"])
    except Parsed as parsed:
        known = parsed.args[0]._option_string_actions
        results.append([f"{arg} (abbreviated)" for arg in argv if arg.startswith("--") and arg.split("=")[0] not in
                        known and not " " in arg])
    except SystemExit as stop:
        results.append([f"exit {stop.code}: " + " ".join(err.getvalue().strip().splitlines()[-1:])])
print(json.dumps(results))
"""


def cases_of(commands: list[tuple[str, str]], folder: str) -> list[tuple[str, str, list[str]]]:
    cases = []
    for where, command in commands:
        match = START.match(command)
        script = match.group("run") or match.group("named") or "svs-depth"
        if script.isupper():  # (python experiments/NAME.py: a name for any of them)
            continue
        assert script == "svs-depth" or script in SCRIPTS, f"{where}: no experiment {script}.py ({command})"
        if script == "bench":  # (svs-depth bench, with --data where it is not given)
            script, command = "svs-depth", "svs-depth bench" + command[match.end():]
            match = START.match(command)
        cases += [(where, script, tokens if script == "svs-depth" else concrete(tokens, folder))
                  for tokens in variants(command[match.end():])]
    return cases


STALE = [("doc.md:1", "python experiments/camera_frames_gate.py --splits held-out --contrast 1"),
         ("doc.md:2", "python experiments/real_rig.py --splits tuned --noise-seeds 0,1"),
         ("doc.md:3", "svs-depth guide --emulator --emulator-noises 4"),
         ("doc.md:4", "python experiments/eval_segmentation.py [--weights FILE] [--sizes 320]")]


def parse_cases(folder: str) -> list[tuple[str, str, list[str]]]:
    """``(where, script, argv)`` of each quoted command and of :data:`STALE`, reports under ``folder``."""
    commands = quoted_commands()
    assert len([c for c in commands if "experiments/real_rig.py" in c[1]]) > 20  # (the extraction sees them)
    return cases_of(commands + STALE, folder)


@pytest.fixture(scope="module")
def checked(experiment_calls) -> dict[str, list]:
    """``where`` -> ``(command, problems)`` of each quoted command and of :data:`STALE` (one process for all, shared
    with test_experiment_options.py's calls: conftest.experiment_calls)."""
    cases, found_all = experiment_calls["commands"]
    out: dict[str, list] = {}
    for (where, script, argv), found in zip(cases, found_all, strict=True):
        out.setdefault(where, []).append((shlex.join([script, *argv]), found))
    return out


def test_every_quoted_experiment_command_parses_with_its_options_in_full(checked):
    stale = [f"{where}: {command}: {found}" for where, rows in checked.items() if not where.startswith("doc.md")
             for command, found in rows if found]
    assert not stale, "\n".join(stale)


def test_a_stale_or_abbreviated_option_in_a_quoted_command_is_caught(checked):
    assert checked["doc.md:1"][0][1] == ["--contrast (abbreviated)"]
    assert checked["doc.md:2"][0][1][0].startswith("exit 2: ") and "--noise-seeds" in checked["doc.md:2"][0][1][0]
    assert checked["doc.md:3"][0][1] == ["--emulator-noises"]
    assert [found for _, found in checked["doc.md:4"]] == [[]]
