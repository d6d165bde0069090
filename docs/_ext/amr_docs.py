"""Sphinx directives that generate mi_amr's reference pages from the code, so that a new
parameter or a new command-line flag appears in the documentation with no other edit.

``.. amr-params::``
    The integrator's parameters, one row each, read from :data:`mi_amr.params.TABLE` when the
    page is built: name, type, default, allowed values, whether ``mi.traverse`` exposes it, and
    its meaning (inline reStructuredText, as the table writes it). An argument
    ``module:NAME`` shows that table of :class:`mi_amr.params.Param` rows instead.

``.. amr-cli::``
    Every command of ``python -m mi_amr``, one section each, read from the argparse parsers of
    :mod:`mi_amr.cli`: the usage line, the command's help and a table of its arguments. An
    argument ``module:NAME`` names another parser factory (called with the program name, as
    ``mi_amr.cli._parser`` is).

Only docutils and Sphinx are used; the functions that gather the rows (:func:`param_rows`,
:func:`cli_commands`) are plain Python, so tests can call them on a modified table or parser.
"""

from __future__ import annotations

import argparse
import importlib
import math
import textwrap

from docutils import nodes
from docutils.parsers.rst import directives
from sphinx.util.docutils import SphinxDirective

PARAM_HEADERS = ("Parameter", "Type", "Default", "Allowed values", "Traversable", "Meaning")
CLI_HEADERS = ("Argument", "Meaning", "Default")
USAGE_WIDTH = 88             # a usage line's wrap, so that it fits the page without scrolling


def _number(x, kind: str) -> str:
    return str(int(x)) if kind == "integer" else f"{x:g}"


def shown_default(p) -> str:
    """How a parameter's default reads on the page."""
    if p.required:
        return "required"
    if p.default is None:
        return "none"
    if isinstance(p.default, bool):
        return "true" if p.default else "false"
    if isinstance(p.default, float):
        return f"{p.default:g}"
    return str(p.default)


def allowed(p) -> str:
    """The parameter's choices or numeric range, as inline reStructuredText ('' if any)."""
    if p.choices:
        return ", ".join(f"``{c}``" for c in p.choices)
    lo, hi = p.lo, p.hi
    if math.isinf(lo) and math.isinf(hi):
        return ""
    if math.isinf(hi):
        return f">= {_number(lo, p.kind)}"
    if math.isinf(lo):
        return f"<= {_number(hi, p.kind)}"
    return f"{_number(lo, p.kind)} to {_number(hi, p.kind)}"


def escape_bars(text: str) -> str:
    """``|grad f|`` is prose in the table, not a reStructuredText substitution: escape every
    ``|`` outside double-backquoted literals."""
    parts = text.split("``")
    return "``".join(p if i % 2 else p.replace("|", "\\|") for i, p in enumerate(parts))


def param_rows(table=None):
    """``(name, type, default, allowed, traversable, meaning)`` strings, one per parameter of
    ``table`` (default: :data:`mi_amr.params.TABLE` as it is when called)."""
    if table is None:
        table = importlib.import_module("mi_amr.params").TABLE
    return [(p.name, p.kind, shown_default(p), allowed(p), "yes" if p.traversable else "no",
             p.meaning) for p in table]


def named(spec: str):
    """``(module, object)`` of ``spec``, ``"module:NAME"`` (the module imported by name)."""
    module_name, _, attr = spec.partition(":")
    module = importlib.import_module(module_name)
    return module, getattr(module, attr)


def _subparsers(parser: argparse.ArgumentParser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            return [(name, sub, helps.get(name) or sub.description or "")
                    for name, sub in action.choices.items()]
    return []


def _argument(parser, action) -> tuple:
    """``(invocation, meaning, default)`` of one argparse action."""
    if action.option_strings:
        invocation = parser._get_formatter()._format_action_invocation(action)
    else:                          # a positional: its name (its choices go in the meaning)
        invocation = action.metavar or action.dest
    meaning = action.help or ""
    if action.choices and not isinstance(action, argparse._SubParsersAction):
        meaning += ("; " if meaning else "") + "one of " + ", ".join(map(str, action.choices))
    if action.required and action.option_strings:
        meaning += ("; " if meaning else "") + "required"
    default = action.default
    if (default in (None, False, [], argparse.SUPPRESS) or not action.option_strings
            or isinstance(action, argparse._StoreTrueAction)):
        shown = ""
    elif isinstance(default, (list, tuple)):
        shown = " ".join(map(str, default))
    else:
        shown = str(default)
    return invocation, meaning, shown


def cli_commands(parser: argparse.ArgumentParser):
    """``(name, usage, help, arguments)`` for every sub-command of ``parser``, in the order the
    parser lists them; ``arguments`` are :func:`_argument` rows (``--help`` left out)."""
    out = []
    for name, sub, help_text in _subparsers(parser):
        rows = [_argument(sub, a) for a in sub._actions
                if not isinstance(a, argparse._HelpAction)]
        usage = " ".join(sub.format_usage().split()).removeprefix("usage: ")
        usage = textwrap.fill(usage, USAGE_WIDTH, subsequent_indent="    ",
                              break_on_hyphens=False)
        out.append((name, usage, help_text, rows))
    return out


def _table(headers, rows, widths):
    """A docutils table; each cell is a list of nodes."""
    table = nodes.table(classes=["longtable"])
    group = nodes.tgroup(cols=len(headers))
    table += group
    for w in widths:
        group += nodes.colspec(colwidth=w)
    head = nodes.thead()
    group += head
    head += nodes.row("", *[nodes.entry("", nodes.paragraph(text=h)) for h in headers])
    body = nodes.tbody()
    group += body
    for cells in rows:
        body += nodes.row("", *[nodes.entry("", nodes.paragraph("", "", *c)) for c in cells])
    return table


class ParamsDirective(SphinxDirective):
    """``.. amr-params::`` -- the integrator's parameter table from mi_amr.params."""

    has_content = False
    optional_arguments = 1

    def _inline(self, text: str):
        found, messages = self.state.inline_text(escape_bars(text), self.lineno)
        return found + messages

    def run(self):
        module, table = named(self.arguments[0] if self.arguments else "mi_amr.params:TABLE")
        self.env.note_dependency(module.__file__)
        rows = []
        for name, kind, default, allow, trav, meaning in param_rows(table):
            rows.append([[nodes.literal(text=name)], [nodes.Text(kind)],
                         [nodes.Text(default)], self._inline(allow), [nodes.Text(trav)],
                         self._inline(meaning)])
        return [_table(PARAM_HEADERS, rows, (14, 10, 10, 12, 8, 46))]


class CliDirective(SphinxDirective):
    """``.. amr-cli::`` -- one section per command of ``python -m mi_amr``."""

    has_content = False
    optional_arguments = 1
    option_spec = {"prog": directives.unchanged}

    def run(self):
        module, factory = named(self.arguments[0] if self.arguments else "mi_amr.cli:_parser")
        self.env.note_dependency(module.__file__)
        parser = factory(self.options.get("prog", "python -m mi_amr"))
        sections = []
        for name, usage, help_text, rows in cli_commands(parser):
            section = nodes.section(ids=[f"cli-{name}"], names=[f"cli-{name}"])
            section += nodes.title("", "", nodes.literal(text=name))
            section += nodes.literal_block(usage, usage, language="text")
            if help_text:
                section += nodes.paragraph(text=help_text[:1].upper() + help_text[1:] + ".")
            cells = [[[nodes.literal(text=inv)], [nodes.Text(meaning)],
                      [nodes.literal(text=d)] if d else []] for inv, meaning, d in rows]
            if cells:
                section += _table(CLI_HEADERS, cells, (30, 60, 10))
            self.state.document.note_explicit_target(section)
            sections.append(section)
        return sections


def setup(app):
    app.add_directive("amr-params", ParamsDirective)
    app.add_directive("amr-cli", CliDirective)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
