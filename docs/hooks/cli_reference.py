"""MkDocs hook: the CLI reference, generated from ``dqskin.cli.build_parser()`` at build time.

A page holding the line ``<!-- cli-reference -->`` gets, in its place, one section per
subcommand: its help, its usage line and a table of its arguments (flags, default, choices,
help) as argparse knows them, so the reference cannot drift from the parser.
"""

import argparse

MARKER = "<!-- cli-reference -->"


def _cell(text):
    return str(text).replace("|", "\\|").replace("*", "\\*").replace("\n", " ")


def _row(action):
    if action.option_strings:
        names = ", ".join(f"`{o}`" for o in action.option_strings)
        if action.nargs != 0:
            names += f" `{action.metavar or action.dest.upper()}`"
    else:
        names = f"`{action.metavar or action.dest.upper()}`"
    default = action.default
    if (action.nargs == 0 or default in (None, argparse.SUPPRESS)
            or not action.option_strings):
        default = ""
    else:
        default = f"`{default}`"
    choices = ", ".join(f"`{c}`" for c in action.choices) if action.choices else ""
    required = " (required)" if action.required and action.option_strings else ""
    return f"| {names}{required} | {default} | {choices} | {_cell(action.help or '')} |"


def _subcommands(parser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield name, helps.get(name, ""), sub


def cli_markdown():
    """Markdown for every subcommand of ``dqskin``."""
    from dqskin.cli import build_parser

    parser = build_parser()
    parts = [f"```\n{parser.format_usage().strip()}\n```", "",
             "Every subcommand also takes `--verbose` (library warnings and Warp's messages).", ""]
    for name, help_text, sub in _subcommands(parser):
        parts += [f"## `dqskin {name}`", "", f"{help_text[:1].upper()}{help_text[1:]}.", "",
                  f"```\n{sub.format_usage().strip()}\n```", "",
                  "| argument | default | choices | meaning |", "|---|---|---|---|"]
        parts += [_row(a) for a in sub._actions
                  if not isinstance(a, argparse._HelpAction) and a.dest != "verbose"]
        parts.append("")
    return "\n".join(parts)


def on_page_markdown(markdown, page, config, files, **kwargs):
    if MARKER in markdown:
        return markdown.replace(MARKER, cli_markdown())
    return markdown
