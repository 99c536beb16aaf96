"""Command line: ``vsidgen build|check|show ...``.

Each command is one ``_add_<name>(subparsers)`` function that registers its
arguments and sets ``handler`` (a function ``(args) -> int``); :data:`COMMANDS`
lists them in the order shown by ``--help``. To add a command, write both and
append the ``_add_`` function to COMMANDS.

User-facing errors (:class:`~vsidgen.errors.VsidgenError`) are printed to
stderr without a traceback and give exit status 2; Ctrl-C gives 130.
"""

from __future__ import annotations

import argparse
import sys

import sympy

from .errors import VsidgenError


def _print_warnings(warnings) -> None:
    for w in warnings:
        print(str(w), file=sys.stderr)


# ---- build -------------------------------------------------------------------

def _add_build(subparsers) -> None:
    p = subparsers.add_parser(
        "build", help="compile specs into generated/<name>.py",
        description="Compile YAML model specs into readable JAX modules (one per spec). "
                    "A module whose embedded spec hash is unchanged is not rewritten.")
    p.add_argument("specs", nargs="+", metavar="SPEC", help="spec file(s) (YAML)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default: the `generated/` folder beside a `specs/` "
                        "folder, else ./generated)")
    p.add_argument("--force", action="store_true", help="rewrite modules even when up to date")
    p.set_defaults(handler=_cmd_build)


def _cmd_build(args) -> int:
    from .codegen import build_model, display_path
    from .model import default_generated_dir
    from .symbolic import compile_spec

    for spec in args.specs:
        symbolic = compile_spec(spec)
        _print_warnings(symbolic.warnings)
        out = args.out if args.out is not None else default_generated_dir(spec)
        result = build_model(symbolic, out_dir=out, force=args.force)
        state = "wrote" if result.written else "up to date"
        print(f"{state}: {display_path(result.module_path)} ({symbolic.name}, "
              f"{len(symbolic.states)} states, {len(symbolic.parameters)} parameters)")
    return 0


# ---- check -------------------------------------------------------------------

def _add_check(subparsers) -> None:
    p = subparsers.add_parser(
        "check", help="validate a spec (and its first data sample)",
        description="Validate a spec: syntax, declarations, equations, definition cycles, "
                    "bounds, noise and data mapping, units. Warnings go to stderr. With --data, "
                    "also evaluate drift and outputs at the first sample of a CSV record. "
                    "Exit status 0 if valid, 2 otherwise.")
    p.add_argument("spec", metavar="SPEC", help="spec file (YAML)")
    p.add_argument("--data", metavar="CSV", default=None,
                   help="a flight record to check the first sample against")
    p.set_defaults(handler=_cmd_check)


def _cmd_check(args) -> int:
    from .symbolic import check_first_sample, compile_spec

    symbolic = compile_spec(args.spec)
    _print_warnings(symbolic.warnings)
    if args.data is not None:
        _print_warnings(check_first_sample(symbolic, args.data))
    n = len(symbolic.warnings)
    print(f"{args.spec}: ok ({symbolic.name}: {len(symbolic.states)} states, "
          f"{len(symbolic.inputs)} inputs, {len(symbolic.outputs)} outputs, "
          f"{len(symbolic.parameters)} parameters; {n} warning{'s' if n != 1 else ''})")
    return 0


# ---- show --------------------------------------------------------------------

def _add_show(subparsers) -> None:
    p = subparsers.add_parser(
        "show", help="print the model equations",
        description="Print the model: states, inputs, outputs, parameters, definitions, "
                    "drift dx/dt = f(x, u, p) and outputs y = h(x, u, p), with units.")
    p.add_argument("spec", metavar="SPEC", help="spec file (YAML)")
    p.add_argument("--latex", action="store_true", help="print the equations as LaTeX")
    p.set_defaults(handler=_cmd_show)


def _unit(u) -> str:
    return f" [{u}]" if u else ""


def _cmd_show(args) -> int:
    from .symbolic import compile_spec

    m = compile_spec(args.spec)
    if args.latex:
        sym = lambda n: sympy.latex(sympy.Symbol(n))  # noqa: E731
        print(r"\begin{align}")
        for n, e in m.definitions:
            print(f"  {sym(n)} &= {sympy.latex(e)} \\\\")
        for v, e in zip(m.states, m.drift):
            print(f"  \\dot{{{sym(v.name)}}} &= {sympy.latex(e)} \\\\")
        for i, (o, e) in enumerate(zip(m.outputs, m.observations)):
            end = " \\\\" if i < len(m.outputs) - 1 else ""
            print(f"  {sym(o.name)}_{{\\mathrm{{meas}}}} &= {sympy.latex(e)}{end}")
        print(r"\end{align}")
        return 0
    print(f"model {m.name}: {m.description}".rstrip(": "))
    print(f"integrator: {m.integrator}, substeps {m.substeps}")
    for title, items in (("states", m.states), ("inputs", m.inputs), ("outputs", m.outputs)):
        print(f"{title}:")
        for v in items:
            print(f"  {v.name}{_unit(v.unit)}{'  ' + v.description if v.description else ''}")
    if m.constants:
        print("constants:")
        for c in m.constants:
            print(f"  {c.name} = {c.value:g}{_unit(c.unit)}{'  (' + c.source + ')' if c.source else ''}")
    if m.parameters:
        print("parameters:")
        for p in m.parameters:
            extra = []
            if p.lower is not None or p.upper is not None:
                extra.append(f"bounds [{p.lower}, {p.upper}]")
            if p.fixed:
                extra.append("fixed")
            print(f"  {p.name}{_unit(p.unit)} initial {p.initial:g}"
                  + (", " + ", ".join(extra) if extra else ""))
    if m.definitions:
        print("definitions:")
        for n, e in m.definitions:
            print(f"  {n} = {sympy.sstr(e)}")
    print("drift:")
    for v, e in zip(m.states, m.drift):
        print(f"  d{v.name}/dt = {sympy.sstr(e)}")
    print("outputs:")
    for o, e in zip(m.outputs, m.observations):
        print(f"  {o.name}{_unit(o.unit)} = {sympy.sstr(e)}")
    return 0


#: subcommand registrars, in --help order (the coordinator appends simulate, fit, report, diagnose)
COMMANDS = [_add_build, _add_check, _add_show]


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vsidgen",
        description="Aircraft system identification from YAML model specs: compile specs to JAX, "
                    "fit them to flight records by variational maximum likelihood, report.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in COMMANDS:
        add(sub)
    return parser


def main(argv=None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 error, 130 interrupted)."""
    parser = make_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or usage error (2)
        return int(exc.code or 0) if isinstance(exc.code, int) else 2
    try:
        return int(args.handler(args) or 0)
    except VsidgenError as err:
        print(str(err), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
