"""The docs: the reference pages (``docs/reference/``) are what ``scripts/gen_reference.py``
writes from the code today, every field of a command or a config has a docstring for them to
show, and the pages build to HTML with MkDocs (``mkdocs.yml``) under ``--strict``: a link to a
page, a file or a heading that does not exist, a link out of ``docs/`` and a page left out of
the nav all fail the build."""

import ast
import dataclasses
import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import sparsecomm

REPO = Path(sparsecomm.__file__).parent.parent
PACKAGE = REPO / "sparsecomm"


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def gen():
    return _load("gen_reference", REPO / "scripts" / "gen_reference.py")


def test_the_reference_pages_are_current(gen):
    for path, text in gen.pages().items():
        where = path.relative_to(REPO)
        assert path.is_file(), f"{where} is missing: run python scripts/gen_reference.py"
        assert path.read_text() == text, f"{where} is not current: run scripts/gen_reference.py"


def test_the_check_mode_finds_a_stale_page(gen, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(gen, "REFERENCE", tmp_path)
    assert gen.main(["--check"]) == 1  # no pages at all
    assert gen.main([]) == 0
    assert gen.main(["--check"]) == 0
    page = tmp_path / gen.CONFIG_PAGE
    page.write_text(page.read_text().replace("Width", "Breadth", 1))
    assert gen.main(["--check"]) == 1
    assert "config.md is not current" in capsys.readouterr().out


def test_the_reference_covers_every_command_and_config(gen):
    commands = (REPO / "docs" / "reference" / "commands.md").read_text()
    config = (REPO / "docs" / "reference" / "config.md").read_text()
    for name, cls in gen.commands().items():
        assert f"\n## {name}\n" in commands
        for field in dataclasses.fields(cls):
            assert f"`--{field.name.replace('_', '-')}" in commands, (name, field.name)
    for cls in gen.config_classes():
        assert f"\n## {cls.__name__}\n" in config
    for name in ("RLConfig", "ILConfig", "ChannelConfig", "NavConfig", "Distributed"):
        assert name in {c.__name__ for c in gen.config_classes()}


def _tyro_commands() -> list[type]:
    """The dataclasses that the package's other command lines parse (``tyro.cli(X, ...)`` with
    ``X`` a dataclass of that module: the deployed agent and world processes, the oracle's GIF),
    found in the source."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr == "cli"
                and isinstance(node.func.value, ast.Name)
                and node.func.value.id == "tyro"
                and node.args
                and isinstance(node.args[0], ast.Name)
            ):
                module = ".".join(path.relative_to(REPO).with_suffix("").parts)
                cls = getattr(importlib.import_module(module), node.args[0].id, None)
                if isinstance(cls, type) and dataclasses.is_dataclass(cls):
                    found.append(cls)
    return found


def test_every_field_of_a_command_or_a_config_has_a_docstring(gen):
    # tyro shows a field's docstring as its --help, and the reference pages show it too.
    # Every class is checked, sparsecomm/deploy/'s included: none lacks one.
    classes = [*gen.commands().values(), *gen.config_classes(), *_tyro_commands()]
    seen = []
    while classes:
        cls = classes.pop()
        if cls not in seen:
            seen.append(cls)
            classes += [sub for _, sub in gen.nested(cls)]
    names = {c.__name__ for c in seen}
    assert {"Train", "Deploy", "AgentArgs", "WorldArgs", "RenderArgs", "NoiseConfig"} <= names
    assert gen.undocumented(seen) == [], "fields without a docstring"


def test_the_docstring_check_names_a_field_without_one(gen, tmp_path):
    source = (
        "import dataclasses\n\n\n"
        "@dataclasses.dataclass\nclass Base:\n"
        '    a: int = 1\n    """Documented."""\n    b: int = 2\n\n\n'
        "@dataclasses.dataclass\nclass Child(Base):\n"
        '    b: int = 3\n    """Documented again, with its new default."""\n'
        "    c: str = ''\n    # a comment is not a docstring\n"
        '    d: float = 0.0\n    e: int = 4\n    """   """\n'
    )
    (tmp_path / "probe_fields.py").write_text(source)
    probe = _load("probe_fields", tmp_path / "probe_fields.py")
    assert gen.undocumented([probe.Base]) == ["probe_fields.Base.b"]
    assert gen.undocumented([probe.Child]) == [
        "probe_fields.Child.c",
        "probe_fields.Child.d",
        "probe_fields.Child.e",
    ]
    assert gen.field_info(probe.Child, "a") == ("int", "Documented.")


def test_docstrings_become_markdown(gen):
    links = {"RLConfig": "config.md#rlconfig"}
    text = gen.markdown(
        "Uses :class:`RLConfig` and ``x_y`` in [0, 1] <here> (docs/budget.md).\n\nMore.",
        "reference/commands.md",
        links,
    )
    assert text == (
        "Uses [`RLConfig`](config.md#rlconfig) and `x_y` in \\[0, 1\\] &lt;here> "
        "([docs/budget.md](../budget.md)).\n\nMore."
    )
    assert gen.value(Path("runs/x")) == "runs/x"
    assert gen.value((0.5,)) == "(0.5,)"


def _mkdocs_build(config: Path, site: Path) -> subprocess.CompletedProcess:
    pytest.importorskip("mkdocs", reason="mkdocs is not installed (the test extra installs it)")
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(config), "-d", str(site)],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_the_docs_build_to_html_with_no_broken_link(tmp_path):
    built = _mkdocs_build(REPO / "mkdocs.yml", tmp_path / "site")
    assert built.returncode == 0, built.stdout + built.stderr
    assert (tmp_path / "site" / "reference" / "config.html").is_file()


def test_a_broken_link_fails_the_build(tmp_path):
    # A copy of the docs with a missing page, a missing heading, a link out of docs/ (to a file
    # that exists, but not in the site) and a page left out of the nav: each is named.
    shutil.copy(REPO / "mkdocs.yml", tmp_path)
    shutil.copytree(REPO / "docs", tmp_path / "docs")
    with open(tmp_path / "docs" / "index.md", "a") as page:
        page.write("\n[a](no-such-page.md) [b](reference/config.md#no-such-heading)\n")
        page.write("[c](../sparsecomm/cli.py)\n")
    (tmp_path / "docs" / "orphan.md").write_text("# Not in the nav\n")
    built = _mkdocs_build(tmp_path / "mkdocs.yml", tmp_path / "site")
    assert built.returncode != 0
    for named in ("no-such-page.md", "#no-such-heading", "../sparsecomm/cli.py", "orphan.md"):
        assert named in built.stdout + built.stderr, named
