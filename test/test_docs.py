"""The docs show commands that work and name files that exist.

Every `mapf-fleet ...` command in a shell block of README.md, docs/*.md and models/README.md is
parsed by the sub-command's own argparse parser (the one its `main` builds), with the shown
arguments: unknown options, bad choices, missing values and missing required options fail. A
`mapf-fleet ...` in running text (an inline code span, often just `mapf-fleet up --record`) is
checked at `--help` level: the sub-command exists and each `--option` it names is one of its
options. Nothing is run: the sub-command's `main` is stopped the moment it calls `parse_args`
(it never reaches rclpy, torch training or a fleet), in a child Python so that the signal
handlers an entry point installs first thing stay out of pytest.

Every repository path the docs name (in code spans, shell blocks and Markdown links) exists;
`{a,b}` alternatives and `*` globs are expanded (a glob must match). Placeholders are written in
capitals (`models/X.md`, `F.yaml`, `RUN/`) and are not checked; neither are paths outside the
repository's own folders (`runs/...`, `bags/...`, `../shared/...`: outputs or beside the checkout).

Shell blocks are fenced ```bash (or sh, console, no language); ```text blocks are not commands.

A link's `#anchor` names a heading of its target (GitHub's anchor of it) or an `<a id="...">` there,
so a reorganised page keeps old links valid with an alias. Code, configs, benchmarks and docs that
cite docs/results.md by section name (`docs/results.md, "Name"`) name one of its headings.
docs/where_to_change.md names files and `module.symbol`s; each file and symbol exists.
"""

from __future__ import annotations

import ast
import json
import re
import shlex
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md")), REPO / "models" / "README.md"]
SHELL_FENCES = {"", "bash", "sh", "shell", "console"}
# The repository's own folders: a path starting with one of these must exist.
REPO_DIRS = {"mapf_fleet", "mapf_fleet_interfaces", "config", "models", "docs", "scripts", "test",
             "benchmarks", "launch", "resource", ".ci"}
# A placeholder component: X.pt, A.pt, F.yaml, X_curves.png, RUN/..., NAME.py
PLACEHOLDER = re.compile(r"(^|[_./-])([A-Z]{1,3}|RUN|NAME|DIR|FILE|ARM|PATH)([_./-]|$)")
SEPARATORS = {"&", "&&", ";", "|", "||"}


# ---- reading the docs ---------------------------------------------------------------------------


def doc_parts(path: Path) -> tuple[list[tuple[int, str]], list[tuple[int, str]], list[tuple[int, str]]]:
    """(shell lines, inline code spans, link targets) of one Markdown file, with line numbers.
    Shell lines ending in a backslash are joined with the next."""
    shell, spans, links = [], [], []
    fence = None  # language of the open fence, None outside
    pending, pending_line = "", 0
    for number, line in enumerate(path.read_text().splitlines(), 1):
        stripped = line.strip()
        if stripped.startswith("```"):
            fence = stripped[3:].strip().lower() if fence is None else None
            continue
        if fence is not None:
            if fence in SHELL_FENCES:
                text = stripped[2:] if stripped.startswith("$ ") else stripped
                if pending:
                    text, number = pending + " " + text, pending_line
                if text.endswith("\\"):
                    pending, pending_line = text[:-1], number
                    continue
                pending = ""
                if text:
                    shell.append((number, text))
            continue
        spans += [(number, m) for m in re.findall(r"`([^`]+)`", line)]
        links += [(number, m) for m in re.findall(r"\]\(([^)\s]+)\)", line)]
    return shell, spans, links


def commands_of(text: str) -> list[list[str]]:
    """The `mapf-fleet` argument lists in one shell line (comments dropped; `a & b` is two;
    `bash scripts/run.sh main ARGS` is `mapf-fleet up ARGS`)."""
    lexer = shlex.shlex(text, posix=True, punctuation_chars=True)  # `a;b` and `a&b` split too
    lexer.whitespace_split, lexer.commenters = True, "#"
    try:
        tokens = list(lexer)
    except ValueError:  # an unclosed quote: not a command line
        return []
    found, current = [], []
    for token in tokens + [";"]:
        if token not in SEPARATORS:
            current.append(token)
            continue
        words = current
        while words and re.fullmatch(r"[A-Za-z_]+=\S*|nice|-n|\d+|do|then|else|time", words[0]):
            words = words[1:]  # VAR=x, nice -n 10, a loop's body
        if words[:3] == ["bash", "scripts/run.sh", "main"]:
            found.append(["up", *words[3:]])
        elif words[:3] == ["bash", "scripts/run.sh", "exec"] and words[3:4] == ["mapf-fleet"]:
            found.append(words[4:])
        elif words[:1] == ["mapf-fleet"]:
            found.append(words[1:])
        current = []
    return found


def path_candidates(text: str) -> list[str]:
    """Words of `text` that name a path inside one of the repository's folders; a module run as
    `python -m mapf_fleet.x.y` names its file (mapf_fleet/x/y.py, or a package's __main__.py)."""
    out = [m.replace(".", "/") + "{.py,/__main__.py}"
           for m in re.findall(r"python3? -m (mapf_fleet[\w.]*)", text)]
    for word in re.split(r"[\s=;()'\"]+", text):
        word = word.rstrip(".,:")
        if "/" not in word or word.startswith(("/", "..", "http")) or "<" in word or "$" in word:
            continue
        if word.split("/")[0] in REPO_DIRS and not PLACEHOLDER.search(word):
            out.append(word)
    return out


def expand_braces(word: str) -> list[str]:
    match = re.search(r"\{([^{}]*)\}", word)
    if not match:
        return [word]
    return [w for alt in match.group(1).split(",")
            for w in expand_braces(word[:match.start()] + alt + word[match.end():])]


def path_exists(word: str, base: Path) -> bool:
    if word.endswith("{.py,/__main__.py}"):  # a module: either file will do
        return any((base / w).is_file() for w in expand_braces(word))
    return all(list(base.glob(w.rstrip("/"))) if "*" in w else (base / w).exists()
               for w in expand_braces(word))


def collect():
    """(full commands, inline commands, paths, links), each item (where, ...)."""
    full, inline, paths, links = [], [], [], []
    for doc in DOCS:
        if not doc.is_file():
            continue
        name = doc.relative_to(REPO).as_posix()
        shell, spans, targets = doc_parts(doc)
        for number, text in shell:
            full += [(f"{name}:{number}", argv) for argv in commands_of(text)]
            paths += [(f"{name}:{number}", p) for p in path_candidates(text)]
        for number, span in spans:
            if span.startswith("mapf-fleet ") and "<" not in span:
                inline += [(f"{name}:{number}", argv) for argv in commands_of(span)]
            paths += [(f"{name}:{number}", p) for p in path_candidates(span)]
        for number, target in targets:
            if re.match(r"[a-z]+:", target):
                continue
            target, _, anchor = target.partition("#")
            if target:
                links.append((f"{name}:{number}", doc.parent, target))
            if anchor and not PLACEHOLDER.search(target):
                ANCHOR_LINKS.append((f"{name}:{number}", (doc.parent / target) if target else doc,
                                     anchor))
    return full, inline, paths, links


# ---- anchors and section names --------------------------------------------------------------------

ANCHOR_LINKS: list[tuple[str, Path, str]] = []  # (where, target file, anchor), filled by collect()


def heading_slug(text: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped (letters, digits,
    `_` and `-` kept), each space a hyphen."""
    text = text.strip().lower().replace("`", "")
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def headings(path: Path) -> list[str]:
    """The heading texts of a Markdown file (outside fenced blocks), backticks dropped."""
    found, fence = [], False
    for line in path.read_text().splitlines():
        if line.strip().startswith("```"):
            fence = not fence
        elif not fence and re.match(r"#{1,6} ", line):
            found.append(line.lstrip("#").strip().replace("`", ""))
    return found


def anchors(path: Path) -> set[str]:
    """Every anchor a link into `path` may name: its headings' (a repeated one gets -1, -2, ...)
    and its `<a id="...">` / `<a name="...">` aliases."""
    seen: dict[str, int] = {}
    out = set()
    for text in headings(path):
        slug = heading_slug(text)
        out.add(f"{slug}-{seen[slug]}" if slug in seen else slug)
        seen[slug] = seen.get(slug, 0) + 1
    out.update(re.findall(r"<a (?:id|name)=\"([^\"]+)\"", path.read_text()))
    return out


RESULTS = REPO / "docs" / "results.md"
CITING = ["mapf_fleet/**/*.py", "test/**/*.py", "benchmarks/**/*.py", "config/**/*.yaml",
          "docs/*.md", "README.md", "models/README.md"]


def results_citations() -> list[tuple[str, str]]:
    """(where, name) for each `results.md, "Name"` / `results.md ("Name")` in code, configs and docs
    (a name broken over comment lines is joined)."""
    found = []
    for pattern in CITING:
        for path in sorted(REPO.glob(pattern)):
            if path.name == "test_docs.py" or path == RESULTS:
                continue
            text = path.read_text()
            for match in re.finditer(r"results\.md", text):
                after = re.sub(r"\s*\n\s*#?\s*", " ", text[match.end():match.end() + 200])
                cited = re.match(r"\)?[,:]?\s*\(?\s*(?:[\"“]([^\"”]{3,120})[\"”]|'(.{3,120}?)'(?!\w))",
                                 after)
                if cited:
                    line = text.count("\n", 0, match.start()) + 1
                    found.append((f"{path.relative_to(REPO)}:{line}", cited.group(1) or cited.group(2)))
    return found


# ---- parsing a command without running it -------------------------------------------------------


def parse_in_child(commands: list[list[str]]) -> list[str]:
    """Run `_check_commands` in a child Python; its verdict per command ('' = parsed)."""
    # the child imports the sub-commands (some import rclpy) and stops at parse_args; it still
    # gets loopback-only discovery, like every process the project starts
    done = subprocess.run([sys.executable, __file__], input=json.dumps(commands), text=True,
                          capture_output=True, cwd=REPO, timeout=600,
                          env={**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"})
    assert done.returncode == 0, f"the parse check failed:\n{done.stdout}\n{done.stderr}"
    return json.loads(done.stdout.strip().splitlines()[-1])


def _check_commands(commands: list[list[str]]) -> list[str]:
    """Each item: [mode, *argv] with mode "full" (parse the arguments) or "options" (the
    sub-command exists and names these options). '' when fine, else why not."""
    import argparse
    import importlib
    import io
    from contextlib import redirect_stderr, redirect_stdout

    from mapf_fleet.cli import COMMANDS

    class Parsed(BaseException):  # not an Exception: no `except Exception` in a main catches it
        def __init__(self, parser, args):
            self.parser, self.args = parser, list(args or [])

    real_parse = argparse.ArgumentParser.parse_args

    def intercept(self, args=None, namespace=None):
        raise Parsed(self, args)

    verdicts = []
    for mode, *argv in commands:
        if not argv or argv[0] not in COMMANDS:
            verdicts.append(f"no sub-command {argv[:1]} (mapf-fleet --help lists {sorted(COMMANDS)})")
            continue
        module, func, _ = COMMANDS[argv[0]]
        argparse.ArgumentParser.parse_args = intercept
        try:  # the shown arguments pick the parser (`evaluate --lifelong` has its own)
            getattr(importlib.import_module(module), func)(argv[1:])
        except Parsed as parsed:
            caught = parsed
        except BaseException as exc:  # noqa: BLE001 - reported as the command's verdict
            verdicts.append(f"stopped before parsing its arguments: {type(exc).__name__}: {exc}")
            continue
        else:
            verdicts.append("returned without calling parse_args")
            continue
        finally:
            argparse.ArgumentParser.parse_args = real_parse
        if mode == "options":
            known = caught.parser._option_string_actions  # every option string of the parser
            unknown = [w.split("=")[0] for w in argv[1:] if w.startswith("--")
                       and w.split("=")[0] not in known]
            verdicts.append(f"unknown option(s) {unknown}" if unknown else "")
            continue
        err = io.StringIO()
        try:
            with redirect_stderr(err), redirect_stdout(io.StringIO()):
                real_parse(caught.parser, caught.args)
            verdicts.append("")
        except SystemExit as exc:
            verdicts.append("" if exc.code == 0 else err.getvalue().strip().splitlines()[-1])
    return verdicts


# ---- the tests ----------------------------------------------------------------------------------

FULL, INLINE, PATHS, LINKS = collect()


def test_the_docs_show_commands():
    """The collector finds the README's commands (an empty list would pass everything)."""
    shown = {argv[0] for _, argv in FULL if argv}
    assert {"up", "train", "evaluate"} <= shown, shown


def test_every_shown_command_parses():
    items = [["full", *argv] for _, argv in FULL] + [["options", *argv] for _, argv in INLINE]
    verdicts = parse_in_child(items)
    bad = [f"{where}: mapf-fleet {shlex.join(argv)}: {verdict}"
           for (where, argv), verdict in zip(FULL + INLINE, verdicts) if verdict]
    assert not bad, "\n".join(bad)


def test_every_named_path_exists():
    missing = sorted({f"{where}: {word}" for where, word in PATHS if not path_exists(word, REPO)})
    assert not missing, "paths named in the docs that do not exist:\n" + "\n".join(missing)


def test_every_link_resolves():
    missing = [f"{where}: {target}" for where, base, target in LINKS
               if not PLACEHOLDER.search(target) and not path_exists(target, base)]
    assert not missing, "links to files that do not exist:\n" + "\n".join(missing)


WHERE_TO_CHANGE = REPO / "docs" / "where_to_change.md"
SYMBOL = re.compile(r"(?:mapf_fleet|test)(?:\.\w+)+")


def symbol_problem(dotted: str) -> str:
    """Why `dotted` (`mapf_fleet.fleet.run.FleetRun.step`, `test.test_layering.LEVELS`) names
    nothing ("" when it names something): its longest prefix that is a module file or package,
    then each further name a definition, assignment or import of the one before, read with `ast`
    (nothing imported: other layers may need rclpy or torch)."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        base = REPO.joinpath(*parts[:cut])
        for module in (base.with_suffix(".py"), base / "__init__.py"):
            if module.is_file():
                return _attribute_problem(module, parts[cut:], dotted)
    return f"{dotted}: no module {parts[0]}"


def _defined_in(body, name: str):
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name == name:
            return node
        targets = (node.targets if isinstance(node, ast.Assign)
                   else [node.target] if isinstance(node, ast.AnnAssign) else [])
        if any(isinstance(t, ast.Name) and t.id == name for t in targets):
            return node
        if isinstance(node, (ast.Import, ast.ImportFrom)) and any(
                (alias.asname or alias.name.split(".")[0]) == name for alias in node.names):
            return node
    return None


def _attribute_problem(module: Path, names: list[str], dotted: str) -> str:
    body = ast.parse(module.read_text()).body
    for depth, name in enumerate(names):
        found = _defined_in(body, name)
        if found is None:
            return f"{dotted}: {module.relative_to(REPO)} has no {'.'.join(names[:depth + 1])}"
        if depth < len(names) - 1:
            if not isinstance(found, ast.ClassDef):
                return f"{dotted}: {'.'.join(names[:depth + 1])} is not a class"
            body = found.body
    return ""


def test_where_to_change_names_exist():
    """docs/where_to_change.md cannot rot: every `mapf_fleet.…` / `test.…` name it gives is defined
    where it says, and every path it names exists."""
    shell, spans, _ = doc_parts(WHERE_TO_CHANGE)
    symbols = sorted({m for _, span in spans for m in SYMBOL.findall(span) if m == span.strip()})
    paths = [p for where, p in PATHS if where.startswith("docs/where_to_change.md:")]
    assert len(symbols) >= 30 and len(paths) >= 10, (symbols, paths)  # the scan finds them
    problems = [problem for problem in map(symbol_problem, symbols) if problem]
    problems += [f"no such path: {p}" for p in paths if not path_exists(p, REPO)]
    assert not problems, ("docs/where_to_change.md names what does not exist (update the page "
                          "to where it moved):\n" + "\n".join(problems))


def test_symbol_problem_catches_a_missing_name():
    assert symbol_problem("mapf_fleet.fleet.run.FleetRun") == ""
    assert symbol_problem("test.test_layering.LEVELS") == ""
    assert symbol_problem("mapf_fleet.cli.COMMANDS") == ""
    assert "has no" in symbol_problem("mapf_fleet.fleet.run.FleetRun.no_such_method")
    assert "has no" in symbol_problem("mapf_fleet.fleet.run.NoSuchClass")
    assert "no module" in symbol_problem("nowhere.x")
    assert symbol_problem("mapf_fleet.no_such_module.thing") != ""
    assert "not a class" in symbol_problem("mapf_fleet.cli.main.x")


def test_every_link_anchor_resolves():
    assert ANCHOR_LINKS, "the collector found no #anchor links (an empty list would pass everything)"
    missing = [f"{where}: {target.name}#{anchor}" for where, target, anchor in ANCHOR_LINKS
               if target.suffix == ".md" and target.is_file() and anchor not in anchors(target)]
    assert not missing, "links to anchors that no heading or <a id> defines:\n" + "\n".join(missing)


def test_results_sections_cited_by_name_exist():
    """A comment or doc that cites docs/results.md by a section's name names one of its headings
    (case aside; a shortened name is fine): the page is reorganised, the citations follow."""
    cited = results_citations()
    assert len(cited) >= 3, cited  # the scan finds the citations it is meant to check
    titles = [re.sub(r"\s+", " ", t).lower() for t in headings(RESULTS)]
    missing = [f"{where}: {name!r}" for where, name in cited
               if not any(re.sub(r"\s+", " ", name.replace("`", "")).lower() in t for t in titles)]
    assert not missing, ("docs/results.md has no section of these names (rename the citation, or "
                         "give the section that name):\n" + "\n".join(missing))


def test_anchor_helpers():
    assert heading_slug("The expert ceiling, second reading: LaCAM with swap") == \
        "the-expert-ceiling-second-reading-lacam-with-swap"
    assert heading_slug("Lifelong throughput (`--lifelong`)") == "lifelong-throughput---lifelong"
    assert heading_slug("The ROS fleet at 128 / 256 robots") == "the-ros-fleet-at-128--256-robots"
    assert heading_slug("Training at the evaluation's density") == "training-at-the-evaluations-density"
    assert "lifelong-throughput" in anchors(RESULTS)
    assert "no-such-section" not in anchors(RESULTS)


@pytest.mark.parametrize("text, expected", [
    ("mapf-fleet up --seed 3 & mapf-fleet up --namespace /b  # two", [["up", "--seed", "3"],
                                                                      ["up", "--namespace", "/b"]]),
    ("bash scripts/run.sh main --num-robots 16", [["up", "--num-robots", "16"]]),
    ("tensorboard --logdir runs/x/tb", []),
    ("for A in a b; do mapf-fleet train --set x=$A; done", [["train", "--set", "x=$A"]]),
])
def test_commands_of(text, expected):
    assert commands_of(text) == expected


def test_a_wrong_command_is_caught():
    """The check fails on what it should fail on: a misspelt option, a bad choice, an unknown
    sub-command, an option the sub-command does not have."""
    verdicts = parse_in_child([["full", "evaluate", "--checkpont", "A.pt"],
                               ["full", "up", "--conflict-rule", "nonsense"],
                               ["full", "launch"],
                               ["options", "train", "--num-robots"],
                               ["full", "evaluate", "--checkpoint", "A.pt", "--sizes", "40"]])
    assert all(verdicts[:4]), verdicts
    assert verdicts[4] == "", verdicts


def test_placeholders_and_paths():
    assert path_candidates("see `models/X.md`, config/fleet/fleet.yaml and runs/a/b") == \
        ["config/fleet/fleet.yaml"]
    assert path_exists("models/eval/dcc_4x25_cl_alpha1.0{,_pibt}.json", REPO)
    assert not path_exists("models/eval/dcc_4x25_cl_alpha1.0{,_nothing}.json", REPO)
    assert not path_exists("config/training/no_such_*.yaml", REPO)
    assert path_candidates("python -m mapf_fleet.ros.stand_in_robot --instance F.yaml") == \
        ["mapf_fleet/ros/stand_in_robot{.py,/__main__.py}"]
    assert path_exists("mapf_fleet/evaluation/model_card{.py,/__main__.py}", REPO)
    assert not path_exists("mapf_fleet/ros/no_such_node{.py,/__main__.py}", REPO)


if __name__ == "__main__":  # the child of parse_in_child: commands on stdin, verdicts on stdout
    print(json.dumps(_check_commands(json.loads(sys.stdin.read()))))
