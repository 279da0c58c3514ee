"""Write the reference pages ``docs/reference/commands.md`` and ``docs/reference/config.md``
from the code: every command of ``sparsecomm`` (``sparsecomm.cli.commands``) and every config
dataclass its arguments hold, each field with its type, its default and its docstring (the
string literal right after the field, which tyro shows in ``--help``).

    python scripts/gen_reference.py          # rewrite the pages
    python scripts/gen_reference.py --check  # exit 1 if a page on disk differs

``tests/test_docs.py`` checks that the pages on disk are what this writes, and that every field
has a docstring (:func:`undocumented`). Imports sparsecomm (and so JAX) but runs nothing.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import re
import sys
import typing
from pathlib import Path, PurePath

REPO = Path(__file__).resolve().parent.parent
REFERENCE = REPO / "docs" / "reference"
COMMANDS_PAGE = "commands.md"
CONFIG_PAGE = "config.md"

ORDER = (
    "LearnerConfig",
    "RLConfig",
    "ILConfig",
    "AgentConfig",
    "ChannelConfig",
    "NoiseConfig",
    "BudgetConfig",
    "ExperimentalConfig",
    "NavConfig",
    "ReferenceConfig",
    "Distributed",
)
"""The config page's order of sections (by class name); a config class not named here follows
them in the order the commands reach it."""


# ---------------------------------------------------------------------------------------------
# Reading the code: each field's annotation and docstring, from the class's source


@functools.cache
def _class_nodes(path: str) -> dict[str, ast.ClassDef]:
    """Every class of the source file ``path``, by its qualified name."""
    found = {}

    def visit(body, prefix):
        for node in body:
            if isinstance(node, ast.ClassDef):
                found[prefix + node.name] = node
                visit(node.body, prefix + node.name + ".")

    visit(ast.parse(Path(path).read_text()).body, "")
    return found


def own_fields(cls: type) -> dict[str, tuple[str, str | None]]:
    """The fields annotated in ``cls``'s own body, in order: ``name -> (annotation as written,
    docstring or None)``. The docstring is the string literal on the statement right after the
    field."""
    node = _class_nodes(inspect.getsourcefile(cls))[cls.__qualname__]
    fields = {}
    for stmt, after in zip(node.body, [*node.body[1:], None], strict=True):
        if not (isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name)):
            continue
        annotation = ast.unparse(stmt.annotation)
        if isinstance(stmt.annotation, ast.Constant) and isinstance(stmt.annotation.value, str):
            annotation = stmt.annotation.value  # a quoted annotation
        doc = None
        if (
            isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            doc = inspect.cleandoc(after.value.value)
        fields[stmt.target.id] = (annotation, doc)
    return fields


def defining_class(cls: type, name: str) -> type:
    """The class of ``cls``'s MRO whose body annotates the field ``name`` (a subclass that
    annotates it again, to change its default, defines it anew)."""
    for klass in cls.__mro__:
        if dataclasses.is_dataclass(klass) and name in own_fields(klass):
            return klass
    raise LookupError(f"{cls.__name__}.{name}: no class of its MRO annotates it")


def field_info(cls: type, name: str) -> tuple[str, str | None]:
    """``(annotation, docstring or None)`` of the field ``name`` of ``cls``, from the class that
    defines it."""
    return own_fields(defining_class(cls, name))[name]


def undocumented(classes) -> list[str]:
    """``Class.field`` for every field of ``classes`` whose defining class gives it no
    docstring (or an empty one)."""
    missing = []
    for cls in classes:
        for f in dataclasses.fields(cls):
            owner = defining_class(cls, f.name)
            doc = own_fields(owner)[f.name][1]
            if not (doc and doc.strip()):
                missing.append(f"{owner.__module__}.{owner.__qualname__}.{f.name}")
    return sorted(set(missing))


def _default(f: dataclasses.Field):
    """A field's default value, ``dataclasses.MISSING`` for a required field."""
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


# ---------------------------------------------------------------------------------------------
# Which classes: the commands, and the config dataclasses their fields hold


def commands() -> dict[str, type]:
    """Every command of ``sparsecomm``, by name, as ``sparsecomm --help`` lists them."""
    from sparsecomm.cli import commands as known

    return {name: cls for name, (cls, _) in known().items()}


def task_configs() -> dict[str, type]:
    """The config class of every task the package registers itself (plug-ins left out), by
    task name."""
    from sparsecomm.envs import registry

    specs = [registry.spec(name) for name in registry.names()]
    return {s.name: s.config for s in specs if s.config.__module__.split(".")[0] == "sparsecomm"}


def nested(cls: type) -> list[tuple[str, type]]:
    """``(field name, config class)`` for each field of ``cls`` that holds a config dataclass:
    the field's type, its default's type, and for a field typed with the tasks' base class
    (``TaskConfig``), every registered task's config."""
    from sparsecomm.envs.task import TaskConfig

    hints = typing.get_type_hints(cls)
    found = []
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        options = [hint, *typing.get_args(hint)]
        default = _default(f)
        if dataclasses.is_dataclass(default) and not isinstance(default, type):
            options.append(type(default))
        if TaskConfig in options:
            options += list(task_configs().values())
        for option in options:
            if isinstance(option, type) and dataclasses.is_dataclass(option):
                if (f.name, option) not in found:
                    found.append((f.name, option))
    return found


def config_classes() -> list[type]:
    """Every config dataclass the commands' arguments hold (at any depth), and their
    dataclass bases with fields, in :data:`ORDER`."""
    seen: list[type] = []

    def visit(cls):
        for base in reversed(cls.__mro__[1:]):
            if dataclasses.is_dataclass(base) and dataclasses.fields(base) and base not in seen:
                seen.append(base)
        for _, sub in nested(cls):
            if sub not in seen:
                seen.append(sub)
                visit(sub)

    for cls in commands().values():
        visit(cls)
    seen = [c for c in seen if dataclasses.fields(c) and c not in commands().values()]
    rank = {name: i for i, name in enumerate(ORDER)}
    return sorted(seen, key=lambda c: (rank.get(c.__name__, len(ORDER)), seen.index(c)))


def flag_prefixes() -> dict[type, list[tuple[str, str]]]:
    """Where each config class is reached from the command line: ``(command, flag prefix)``
    pairs, such as ``("train", "--config.agent.")``."""
    where: dict[type, list[tuple[str, str]]] = {}

    def visit(command, cls, prefix):
        for name, sub in nested(cls):
            flag = prefix + _flag_name(name) + "."
            if (command, flag) not in where.setdefault(sub, []):
                where[sub].append((command, flag))
            visit(command, sub, flag)

    for command, cls in commands().items():
        visit(command, cls, "--")
    return where


# ---------------------------------------------------------------------------------------------
# Writing Markdown


_ROLE = re.compile(r":[a-z]+:`(~?)([^`]+)`")
_CODE = re.compile(r"``(.+?)``|`([^`]+)`")
_DOCS_PAGE = re.compile(r"\bdocs/[\w/-]+(?:\.[\w-]+)*\.md\b")
_ESCAPE = re.compile(r"([\\_\[\]])")


def _escape(text: str) -> str:
    """Plain text as Markdown that shows it as it is; ``*`` is left as it is (``**strong**``
    means the same in a docstring and in Markdown)."""
    return _ESCAPE.sub(r"\\\1", text).replace("<", "&lt;")


def _plain(text: str, page: str) -> str:
    """Plain text (no code) as Markdown, each ``docs/PAGE.md`` it names a link to that page."""
    out, last = [], 0
    for m in _DOCS_PAGE.finditer(text):
        target = Path(m.group(0)).relative_to("docs")
        href = Path(*([".."] * (len(Path(page).parts) - 1)), target).as_posix()
        out += [_escape(text[last : m.start()]), f"[{_escape(m.group(0))}]({href})"]
        last = m.end()
    return "".join([*out, _escape(text[last:])])


def markdown(doc: str, page: str, anchors: dict[str, str]) -> str:
    """A docstring (reStructuredText-ish: ````code````, ``:class:`X```) as Markdown for
    ``page`` (its path under docs/): paragraphs joined by a blank line, each on one line; a
    class documented on the reference pages becomes a link to its section (``anchors``)."""
    paragraphs = [" ".join(p.split()) for p in re.split(r"\n\s*\n", inspect.cleandoc(doc))]
    out = []
    for text in paragraphs:
        text = _ROLE.sub(lambda m: f"`{m[2].rpartition('.')[2] if m[1] else m[2]}`", text)
        parts, last = [], 0
        for m in _CODE.finditer(text):
            code = m.group(1) or m.group(2)
            parts.append(_plain(text[last : m.start()], page))
            name = code.rpartition(".")[2]
            if name in anchors:
                parts.append(f"[`{code}`]({_href(anchors[name], page)})")
            else:
                parts.append(f"`{code}`" if "`" not in code else f"`` {code} ``")
            last = m.end()
        parts.append(_plain(text[last:], page))
        out.append("".join(parts))
    return "\n\n".join(out)


def _href(anchor: str, page: str) -> str:
    """A link from ``page`` to ``anchor`` (``config.md#rlconfig``), both under docs/reference."""
    target, _, fragment = anchor.partition("#")
    return f"#{fragment}" if Path(page).name == target else anchor


def _flag_name(name: str) -> str:
    return name.replace("_", "-")


def value(v) -> str:
    """A default as Python writes it; a path as its text; a config dataclass as its class and
    the fields that differ from that class's defaults."""
    if v is dataclasses.MISSING:
        return "required"
    if isinstance(v, PurePath):
        return v.as_posix()
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        changed = []
        for f in dataclasses.fields(v):
            default, now = _default(f), getattr(v, f.name)
            if default is dataclasses.MISSING or now != default:
                changed.append(f"{f.name}={value(now)}")
        return f"{type(v).__name__}({', '.join(changed)})"
    if isinstance(v, tuple):
        items = [value(x) for x in v]
        return "(" + ", ".join(items) + ("," if len(items) == 1 else "") + ")"
    return repr(v)


def _item(head: str, annotation: str, default, doc: str | None, page: str, anchors) -> str:
    """One field as a list item: its name or flag, type, default, then its docstring."""
    body = markdown(doc, page, anchors) if doc else "(no docstring)"
    body = body.replace("\n\n", "\n\n    ")  # a later paragraph stays in the item
    shown = value(default)
    default_text = "required" if shown == "required" else f"default `{shown}`"
    return f"- **{head}** (`{annotation}`, {default_text}): {body}"


def _intro(cls: type, page: str, anchors) -> str:
    return markdown(cls.__doc__ or "", page, anchors)


def _anchor(cls: type) -> str:
    return cls.__name__.lower()


def anchors() -> dict[str, str]:
    """Every config class documented on the config page, by name: its link target."""
    return {c.__name__: f"{CONFIG_PAGE}#{_anchor(c)}" for c in config_classes()}


HEADER = (
    "<!-- Generated by scripts/gen_reference.py from the code's docstrings: edit those, then "
    "run `python scripts/gen_reference.py` (tests/test_docs.py checks the page is current). -->"
)


def commands_page() -> str:
    """The text of ``docs/reference/commands.md``."""
    from sparsecomm import learners
    from sparsecomm.configs import PRESETS

    page = f"reference/{COMMANDS_PAGE}"
    links = anchors()
    tasks = task_configs()
    lines = [
        HEADER,
        "",
        "# Commands",
        "",
        "Every command of `sparsecomm` and its flags, from the code's own docstrings (the same "
        "text as `sparsecomm COMMAND --help`). A flag `--a.b` sets the field `b` of the config "
        f"held in the field `a`; the config dataclasses are on [the config page]({CONFIG_PAGE}). "
        "A boolean field `x` is set with `--x` and unset with `--no-x`; a tuple takes several "
        "values (`--lams 0 0.01`). Defaults are written as Python writes them.",
        "",
        "| command | what it does |",
        "|---|---|",
    ]
    for name, cls in commands().items():
        summary = " ".join((cls.__doc__ or "").split()).split(". ")[0].rstrip(".")
        lines.append(f"| [`{name}`](#{name}) | {markdown(summary, page, links)} |")
    for name, cls in commands().items():
        lines += [
            "",
            f"## {name}",
            "",
            f"`sparsecomm {name}`: `{cls.__module__}.{cls.__qualname__}`.",
            "",
            _intro(cls, page, links),
            "",
        ]
        if name in learners.COMMANDS:
            presets = [p for p in PRESETS if name in PRESETS[p]]
            task_list = ", ".join(
                f"`{t}` ([`{c.__name__}`]({_href(links[c.__name__], page)}))"
                for t, c in tasks.items()
            )
            lines += [
                "- **`--preset NAME`** (given before the others): start every field from a named "
                "preset, one of " + ", ".join(f"`{p}`" for p in presets) + f" ([the presets]"
                f"({CONFIG_PAGE}#presets)); the flags after it override it.",
                "- **`--task NAME`** (given before the others): start `--config.env.*` from a "
                f"registered task's defaults: {task_list}, or a task of one's own "
                "(`SPARSECOMM_TASKS`, [plugin.md](../plugin.md)).",
            ]
        hints = typing.get_type_hints(cls)
        held = {f: sub for f, sub in nested(cls)}
        for f in dataclasses.fields(cls):
            annotation, doc = field_info(cls, f.name)
            flag = "--" + _flag_name(f.name)
            if f.name in held:
                sub = held[f.name]
                head = f"`{flag}.*`"
                doc = (doc or "") + f" Its fields: :class:`{sub.__name__}`."
            elif hints[f.name] is bool:
                head = f"`{flag}` / `--no-{_flag_name(f.name)}`"
            else:
                head = f"`{flag}`"
            lines.append(_item(head, annotation, _default(f), doc, page, links))
    return "\n".join(lines) + "\n"


def config_page() -> str:
    """The text of ``docs/reference/config.md``."""
    from sparsecomm import configs

    page = f"reference/{CONFIG_PAGE}"
    links = anchors()
    classes = config_classes()
    where = flag_prefixes()
    lines = [
        HEADER,
        "",
        "# Configuration",
        "",
        "Every config dataclass the [commands](commands.md) hold, field by field, from the "
        "code's own docstrings. A docstring says each field's rule, its unit and where its "
        "default comes from: `paper` (stated in the paper, [paper.md](../paper.md)), `SPEC` "
        "(pinned by [spec.md](../spec.md)) or `ours` (chosen here, by the measurements of the "
        "page named). In Python: `RLConfig(agent=AgentConfig(hidden=32))`; on the command line: "
        "`sparsecomm train --config.agent.hidden 32`.",
        "",
        "| class | module | on the command line |",
        "|---|---|---|",
    ]
    for cls in classes:
        reached = _reached(where.get(cls, [])) or "(a base)"
        lines.append(f"| [`{cls.__name__}`](#{_anchor(cls)}) | `{cls.__module__}` | {reached} |")
    for cls in classes:
        lines += ["", f"## {cls.__name__}", "", f"`{cls.__module__}.{cls.__qualname__}`"]
        bases = [b for b in cls.__mro__[1:] if b in classes]
        if bases:
            base = bases[0]
            lines[-1] += (
                f", a subclass of [`{base.__name__}`](#{_anchor(base)}): its fields, and those "
                "below (a field below with the same name changes that field's default)"
            )
        lines[-1] += "."
        reached = _reached(where.get(cls, []))
        if reached:
            lines[-1] += f" On the command line: {reached}."
        lines += ["", _intro(cls, page, links), ""]
        own = own_fields(cls)
        for f in dataclasses.fields(cls):
            if f.name in own:
                annotation, doc = own[f.name]
                lines.append(_item(f"`{f.name}`", annotation, _default(f), doc, page, links))
    lines += [
        "",
        "## Presets",
        "",
        "`sparsecomm.configs.PRESETS`, and the commands each serves:",
        "",
    ]
    for name, by_command in configs.PRESETS.items():
        lines.append(f"- `{name}`: " + ", ".join(f"`{c}`" for c in by_command))
    lines += ["", markdown(_constant_doc(configs, "PRESETS"), page, links)]
    return "\n".join(lines) + "\n"


def _reached(pairs: list[tuple[str, str]]) -> str:
    """``sparsecomm train --config.agent.*, ...``: one entry per flag prefix, its commands."""
    by_prefix: dict[str, list[str]] = {}
    for command, prefix in pairs:
        by_prefix.setdefault(prefix, []).append(command)
    return ", ".join(
        f"`{prefix}*` ({', '.join(f'`{c}`' for c in cmds)})" for prefix, cmds in by_prefix.items()
    )


def _constant_doc(module, name: str) -> str:
    """The docstring written after the module-level assignment of ``name``."""
    body = ast.parse(Path(inspect.getsourcefile(module)).read_text()).body
    for stmt, after in zip(body, body[1:], strict=False):
        targets = stmt.targets if isinstance(stmt, ast.Assign) else [getattr(stmt, "target", None)]
        if any(isinstance(t, ast.Name) and t.id == name for t in targets):
            if isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant):
                return after.value.value
    raise LookupError(f"{module.__name__}.{name} has no docstring")


def pages() -> dict[Path, str]:
    """Every reference page, by its path, as this script writes it."""
    return {REFERENCE / COMMANDS_PAGE: commands_page(), REFERENCE / CONFIG_PAGE: config_page()}


def stale() -> list[Path]:
    """The reference pages whose text on disk differs from what this script writes."""
    return [p for p, text in pages().items() if not p.is_file() or p.read_text() != text]


def _shown(path: Path) -> str:
    return str(path.relative_to(REPO) if path.is_relative_to(REPO) else path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if a page is not current")
    args = parser.parse_args(argv)
    if args.check:
        out = stale()
        for path in out:
            print(f"{_shown(path)} is not current: run python scripts/gen_reference.py")
        return 1 if out else 0
    REFERENCE.mkdir(parents=True, exist_ok=True)
    for path, text in pages().items():
        path.write_text(text)
        print(f"wrote {_shown(path)} ({len(text.encode())} bytes)")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))  # this checkout's sparsecomm, not another one installed
    sys.exit(main())
