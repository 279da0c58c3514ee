"""The package's layering, read from its source: no import cycle, nothing imports the command
line, and ``channel/`` and ``envs/`` stand alone at the bottom. And the repository's files, read
from git: no file names a work session or an issue number, and every result file under
``docs/results/`` is named by a page, a script, a test or the code."""

import ast
import fnmatch
import posixpath
import re
import subprocess
from pathlib import Path

import pytest

import sparsecomm

ROOT = Path(sparsecomm.__file__).parent
REPO = ROOT.parent


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The sparsecomm modules ``path`` imports anywhere (top level or inside functions)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{a.name}" for a in node.names] + [base]
        else:
            continue
        for t in targets:
            while t and t not in modules:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def _graph() -> dict[str, set[str]]:
    paths = sorted(ROOT.rglob("*.py"))
    modules = {_module_name(p) for p in paths}
    return {_module_name(p): _imports(p, modules) for p in paths}


def test_import_graph_has_no_cycle():
    graph = _graph()
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node, path):
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = path[path.index(nxt) :] + [nxt]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])


def test_nothing_imports_the_command_line():
    importers = sorted(m for m, deps in _graph().items() if "sparsecomm.cli" in deps)
    assert importers == []


def test_channel_and_envs_stand_alone():
    graph = _graph()
    for layer in ("sparsecomm.channel", "sparsecomm.envs"):
        for module, deps in graph.items():
            if module == layer or module.startswith(layer + "."):
                outside = sorted(d for d in deps if not d.startswith(layer) and d != "sparsecomm")
                assert outside == [], (module, outside)


def test_the_graph_reader_sees_real_imports():
    graph = _graph()
    # Known edges, top level and inside a package: the reader must find them.
    assert "sparsecomm.channel.quantizer" in graph["sparsecomm.channel.codes"]
    assert "sparsecomm.learner" in graph["sparsecomm.rl"]
    assert "sparsecomm.experiment" in graph["sparsecomm.cli"]


def _private_uses(path: Path, modules: set[str], source: str | None = None) -> list[str]:
    """Where ``path`` (or ``source`` read as that file) reaches into another sparsecomm module
    for a ``_private`` name: ``from sparsecomm.X import _name``, or ``X._name`` with ``X`` a
    sparsecomm module it imported."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text() if source is None else source)
    aliases: dict[str, str] = {}  # local name -> the sparsecomm module it is bound to
    found = []

    def private(attr: str) -> bool:
        return attr.startswith("_") and not attr.endswith("__")

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name in modules and a.asname:
                    aliases[a.asname] = a.name
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            if base not in modules or base == name:
                continue
            for a in node.names:
                if f"{base}.{a.name}" in modules:
                    aliases[a.asname or a.name] = f"{base}.{a.name}"
                elif private(a.name):
                    found.append(f"{name}:{node.lineno}: from {base} import {a.name}")
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and aliases.get(node.value.id, name) != name
            and private(node.attr)
        ):
            found.append(f"{name}:{node.lineno}: {aliases[node.value.id]}.{node.attr}")
    return found


def test_no_module_uses_another_modules_private_names():
    paths = sorted(ROOT.rglob("*.py"))
    modules = {_module_name(p) for p in paths}
    found = [use for p in paths for use in _private_uses(p, modules)]
    assert found == [], "private names used across modules:\n" + "\n".join(found)


def test_the_private_name_reader_sees_both_forms():
    # A module of the package (never written), read from ``source``.
    probe = ROOT / "probe.py"
    modules = {"sparsecomm", "sparsecomm.experiment", "sparsecomm.probe"}
    source = (
        "from sparsecomm.experiment import _at_least, load_run\n"
        "from sparsecomm import experiment as ex\n"
        "ex._check_index(1, 2), ex.load_run, ex.__doc__\n"
    )
    uses = _private_uses(probe, modules, source)
    assert uses == [
        "sparsecomm.probe:1: from sparsecomm.experiment import _at_least",
        "sparsecomm.probe:3: sparsecomm.experiment._check_index",
    ]


def test_run_folders_sit_below_the_commands_and_deploy():
    # The run folder's module serves experiment, codestats and deploy: it imports none of them,
    # and deploy reads run folders through it, not through experiment.
    graph = _graph()
    above = ("sparsecomm.experiment", "sparsecomm.codestats", "sparsecomm.cli", "sparsecomm.deploy")
    assert sorted(d for d in graph["sparsecomm.runfolder"] if d.startswith(above)) == []
    for module, deps in graph.items():
        if module.startswith("sparsecomm.deploy"):
            assert "sparsecomm.experiment" not in deps, module


def test_only_the_run_folder_module_names_the_exported_team_files():
    # One writer and one reader of an exported team: no other module's code (docstrings aside)
    # spells its file names.
    found = []
    for path in sorted(ROOT.rglob("*.py")):
        if _module_name(path) == "sparsecomm.runfolder":
            continue
        tree = ast.parse(path.read_text())
        docs = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr)}
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Constant)
                and isinstance(node.value, str)
                and id(node) not in docs
                and ("team.json" in node.value or "actor.msgpack" in node.value)
            ):
                found.append(f"{_module_name(path)}:{node.lineno}: {node.value!r}")
    assert found == [], "\n".join(found)


def _mode_comparisons(source: str) -> list[int]:
    """Lines of ``source`` that compare a ``.mode`` attribute with anything (``==``, ``!=``,
    ``in``, ``not in``): what a caller should ask ``ChannelConfig`` instead."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            if any(isinstance(s, ast.Attribute) and s.attr == "mode" for s in sides):
                lines.append(node.lineno)
    return lines


def test_only_the_channel_compares_channel_modes():
    # Callers ask ChannelConfig what its mode does (speaks, quantizes, sends_symbols, ...), so a
    # new mode is written in channel/ alone.
    assert _mode_comparisons("if cfg.channel.mode == 'off':\n    pass\nx = c.mode in M\n") == [1, 3]
    found = [
        f"{_module_name(p)}:{line}"
        for p in sorted(ROOT.rglob("*.py"))
        if not _module_name(p).startswith("sparsecomm.channel")
        for line in _mode_comparisons(p.read_text())
    ]
    assert found == [], "mode strings compared outside channel/:\n" + "\n".join(found)


LINK_RULES = {"link_gate", "on_silence", "holds", "news_margin", "news_gate", "last_delivered"}
"""The link rules' fields and primitives: ``ChannelConfig.build`` (``channel/team.py``) reads
them for everyone else."""


def _link_rule_reads(source: str) -> list[int]:
    """Lines of ``source`` that read a link rule's field (an attribute, ``cfg.holds``)."""
    return sorted(
        node.lineno
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.Attribute) and node.attr in LINK_RULES
    )


def test_only_the_channel_reads_the_link_rules():
    # A new link rule is written in channel/ alone: the rollout, a team expert and a deployed
    # agent step their links through the channel built once from its config.
    assert _link_rule_reads("a = cfg.channel.holds\nb = ChannelConfig(link_gate=True)\n") == [1]
    found = [
        f"{_module_name(p)}:{line}"
        for p in sorted(ROOT.rglob("*.py"))
        if not _module_name(p).startswith("sparsecomm.channel")
        for line in _link_rule_reads(p.read_text())
    ]
    assert found == [], "link rules read outside channel/:\n" + "\n".join(found)


def test_deploy_draws_no_dither_and_rebuilds_no_message_of_its_own():
    # A deployed agent runs the channel's own sender and receiver sides (channel.transmit,
    # channel.receive, channel.dither_links): none of the quantizer's primitives appear in
    # deploy/.
    primitives = {"dither", "dither_key", "dequantize", "quantize", "quantize_dithered"}
    found = []
    for path in sorted((ROOT / "deploy").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            name = node.attr if isinstance(node, ast.Attribute) else getattr(node, "id", None)
            if name in primitives:
                found.append(f"{_module_name(path)}:{node.lineno}: {name}")
    assert found == [], "\n".join(found)


STRICT_PARSERS = {("channel/frames.py", "decode_frame")}
"""Functions allowed past the length limit: a parser that checks every byte, read top to bottom."""


def _long_functions(limit: int) -> list[str]:
    """Every function (nested ones inside their parent's count) longer than ``limit`` lines."""
    found = []
    for path in sorted(ROOT.rglob("*.py")):
        where = path.relative_to(ROOT).as_posix()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > limit and (where, node.name) not in STRICT_PARSERS:
                    found.append(f"{where}:{node.lineno} {node.name} ({lines} lines)")
    return found


def test_no_function_is_over_80_lines_except_strict_parsers():
    assert _long_functions(80) == []
    assert _long_functions(40), "the reader finds no function at all"


def test_the_rollout_step_reads_in_at_most_60_lines():
    """Whatever a step may be is decided before the scan (``rollout._Plan``: the action rule,
    the link rule, what is kept); the step, ``rollout._step``, reads act, talk, step, record."""
    tree = ast.parse((ROOT / "rollout.py").read_text())
    (step,) = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "_step"]
    assert step.end_lineno - step.lineno + 1 <= 60


def test_tasks_are_found_by_name_not_by_class():
    """Outside ``envs/``, no module builds or names a task's class: they go through the
    registry (``envs.registry.make``) and the task interface (``envs.task``)."""
    named = []
    for path in sorted(ROOT.rglob("*.py")):
        where = path.relative_to(ROOT).as_posix()
        if where.startswith("envs/"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Name | ast.alias):
                name = node.id if isinstance(node, ast.Name) else node.name
                if name in ("NavigationEnv", "NavigationTask", "SimpleReference"):
                    named.append(f"{where}:{node.lineno if hasattr(node, 'lineno') else ''} {name}")
    assert named == []


def test_only_the_command_line_imports_the_pipelines():
    # The paper's pipelines sit above the library: no module outside sparsecomm/pipelines/
    # reaches into them, except the command line that runs them.
    pipelines = "sparsecomm.pipelines"
    found = sorted(
        module
        for module, deps in _graph().items()
        if not (module == pipelines or module.startswith(pipelines + "."))
        and module != "sparsecomm.cli"
        and any(d == pipelines or d.startswith(pipelines + ".") for d in deps)
    )
    assert found == []
    assert "sparsecomm.pipelines.reproduce" in _graph()["sparsecomm.cli"]


def _tracked() -> list[str]:
    """The repository's tracked files that exist, as paths from its root; skips outside a git
    checkout (an installed package has no docs to check)."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return [p for p in listed.decode().split("\0") if p and (REPO / p).is_file()]


def _text(path: str) -> str | None:
    """The text of the tracked file ``path``, or None for a binary one (a NUL byte, not UTF-8)."""
    data = (REPO / path).read_bytes()
    if b"\0" in data:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


WORK_LOG = re.compile(r"(?<![a-z])(?:session|issue)s?[\s_-]*#?\d", re.IGNORECASE)
"""A work session or an issue named by its number: either word, singular or plural, then
spaces (a line break too), ``_`` or ``-``, an optional ``#`` and a digit. ``_`` and ``-`` make
it catch file names; no letter may come before the word. The pattern's own text does not match
it (a ``|`` or ``)`` follows each word)."""


def _work_log(text: str) -> list[tuple[int, str]]:
    """``(line number, line)`` for each line of ``text`` where a match of ``WORK_LOG``
    starts."""
    lines = text.splitlines()
    found = []
    for match in WORK_LOG.finditer(text):
        number = text.count("\n", 0, match.start()) + 1
        line = lines[number - 1].strip()
        if (number, line) not in found:
            found.append((number, line))
    return found


def test_the_work_log_check_flags_sessions_and_issues_and_passes_the_rest():
    # numbers interpolated, so that this file's own text names no session or issue
    for story in [
        f"measured in session {28} with 4000 updates",
        f"(docs/paper-task.md, sessions {22} and 24)",
        f"open work (issue {7})",
        f"Issue {14}'s target: budget 16",
        f"see issue #{5}",
        f"docs/results/paper/rl_b32_session{32}/summary.json",
        f"the figures of session-{9}",
        f"in session\n  {24}'s run",
    ]:
        assert _work_log(story), story
    assert _work_log(f"a\nb in session\n{24}") == [(2, "b in session")]
    for fine in [
        "proc = subprocess.Popen(cmd, start_new_session=True)",
        "a TensorBoard session START at step S",
        "the decoder issues no warning",
        f"tissue {3}, reissue {2}",
        "issues of 2 kinds",
    ]:
        assert not _work_log(fine), fine


def test_no_tracked_file_names_a_work_session_or_an_issue():
    """The repository speaks of the library, not of how it was made: no tracked file's path or
    text names a work session or an issue by its number (state the rule, the figure, the
    command, the seeds, the hardware, a date or a commit instead)."""
    found = []
    for path in _tracked():
        if WORK_LOG.search(path):
            found.append(f"{path}: the file's path")
        text = _text(path)
        if text is not None:
            found += [f"{path}:{n}: {line}" for n, line in _work_log(text)]
    assert not found, "work sessions or issue numbers:\n" + "\n".join(found)


RESULTS = "docs/results"
PATH_TOKEN = re.compile(r"[\w.*/-]+")
NAME_GLOB = re.compile(r"\w[\w.-]*\*[\w.*-]*")


def _results_named_in(source: str, text: str, results: set[str]) -> set[str]:
    """The files of ``results`` (paths under ``docs/results/``) that ``text``, the file
    ``source``, names: by their path from the repository's root or from ``source``'s folder
    (a report's ``x.png`` beside it), by
    a glob of such paths (``results/noise/*.png``), or by their file name or a glob of names
    (``comm_*``) where ``text`` also names a folder above them, or a file in such a folder
    (`` `docs/results/wire/a.json`, `b.json` ``)."""
    folders = {posixpath.dirname(r) for r in results}
    for folder in list(folders):
        while folder.startswith(RESULTS + "/"):
            folders.add(folder)
            folder = posixpath.dirname(folder)
    found, named_folders, names = set(), set(), set()
    for token in set(PATH_TOKEN.findall(text)):
        token = token.rstrip(".")
        if "/" not in token:
            names.add(token)
        for base in ("", posixpath.dirname(source)):
            path = posixpath.normpath(posixpath.join(base, token))
            if "*" in path and path.startswith(RESULTS + "/"):
                found |= {r for r in results if fnmatch.fnmatchcase(r, path)}
            elif path in results:
                found.add(path)
                named_folders.add(posixpath.dirname(path))
            elif path in folders:
                named_folders.add(path)
    globs = [n for n in names if NAME_GLOB.fullmatch(n)]
    for r in results:
        name = posixpath.basename(r)
        if any(r.startswith(folder + "/") for folder in named_folders) and (
            name in names or any(fnmatch.fnmatchcase(name, g) for g in globs)
        ):
            found.add(r)
    return found


def test_the_results_reader_sees_paths_globs_and_names_beside_their_folder():
    results = {
        "docs/results/a/x.json",
        "docs/results/a/x.png",
        "docs/results/a/b/y.json",
        "docs/results/a/comm_curves.png",
        "docs/results/c/z.json",
        "docs/results/c/w.json",
    }
    page = "`results/a/x.json`, `y.json` and `comm_*`; figures: `docs/results/a/*.png`; `w.json`"
    assert _results_named_in("docs/page.md", page, results) == {
        "docs/results/a/x.json",
        "docs/results/a/x.png",
        "docs/results/a/b/y.json",
        "docs/results/a/comm_curves.png",
    }
    # A folder alone names none of its files; a name with its folder does.
    assert _results_named_in("s.py", 'Path("docs/results/c")', results) == set()
    assert _results_named_in("s.py", '"docs/results/c" / "z.json"', results) == {
        "docs/results/c/z.json"
    }
    # A report inside docs/results names its figures relative to itself.
    assert _results_named_in("docs/results/a/report.md", "![](x.png) ![](b/y.json)", results) == {
        "docs/results/a/x.png",
        "docs/results/a/b/y.json",
    }


def test_every_result_file_is_named_outside_docs_results():
    """Every file under ``docs/results/`` is named by a tracked file outside it (a page, a
    script, a test, the code) or by a page under it that is itself named (a report's figures):
    a result no page names is either linked where its run is described or deleted (git keeps
    it)."""
    tracked = _tracked()
    results = {p for p in tracked if p.startswith(RESULTS + "/")}
    queue = [p for p in tracked if not p.startswith(RESULTS + "/")]
    named = set()
    while queue:
        source = queue.pop()
        text = _text(source)
        if text is None:
            continue
        for path in _results_named_in(source, text, results) - named:
            named.add(path)
            if path.endswith(".md"):
                queue.append(path)
    unnamed = sorted(results - named)
    assert not unnamed, "result files no page, script, test or code names:\n" + "\n".join(unnamed)
