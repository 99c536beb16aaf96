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
import math
import pathlib
import sys

from .compilecache import enable_compilation_cache
from .errors import VsidgenError, eprint, printable
from .spec.overrides import add_override_arguments, overrides_of, read_estimates


def _print_warnings(warnings) -> None:
    for w in warnings:
        eprint(str(w))


# ---- build -------------------------------------------------------------------

def _add_build(subparsers) -> None:
    p = subparsers.add_parser(
        "build", help="compile specs into generated/<name>.py",
        description="Compile YAML model specs into readable JAX modules (one per spec). "
                    "A module whose embedded spec hash is unchanged is not rewritten.")
    p.add_argument("specs", nargs="+", metavar="SPEC", help="spec file(s) (YAML)")
    p.add_argument("-o", "--out", default=None, metavar="DIR",
                   help="output folder (default: the `generated/` folder beside a `specs/` "
                        "folder, else ./generated)")
    p.add_argument("--force", action="store_true", help="rewrite modules even when up to date")
    p.set_defaults(handler=_cmd_build)


def _cmd_build(args) -> int:
    from .codegen import build_model, display_path
    from .model import default_generated_dir
    from .spec import compile_spec

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
        "check", help="validate a spec (and a data record)",
        description="Validate a spec: syntax, declarations, equations, definition cycles, "
                    "bounds, noise and data mapping, units. Warnings go to stderr. With --data, "
                    "also check the whole record (CSV or MATLAB .mat) through the data map: time "
                    "increasing and uniform, inputs present, value ranges plausible for their "
                    "units, drift and outputs finite at every sample. "
                    "Exit status 0 if valid, 2 otherwise.")
    p.add_argument("spec", metavar="SPEC", help="spec file (YAML)")
    # the record positionally too, as `vsidgen fit SPEC DATA` takes it (a new user's first try)
    rec = p.add_mutually_exclusive_group()
    rec.add_argument("record", metavar="DATA", nargs="?", default=None,
                     help="a flight record (CSV or .mat) to check against the spec")
    rec.add_argument("--data", metavar="DATA", default=None, help="the same, as an option")
    p.set_defaults(handler=_cmd_check)


def _cmd_check(args) -> int:
    from .data.check import check_record
    from .spec import compile_spec
    from .spec.identifiability import symmetry_warnings

    symbolic = compile_spec(args.spec)
    _print_warnings(symbolic.warnings)
    symmetric = symmetry_warnings(symbolic)
    _print_warnings(symmetric)
    data_warnings = []
    data = args.data if args.data is not None else args.record
    if data is not None:
        data_warnings = check_record(symbolic, data, start=_fit_start(args.spec, symbolic))
        _print_warnings(data_warnings)
        _print_ranges(symbolic, data)
    n = len(symbolic.warnings) + len(symmetric) + len(data_warnings)
    print(f"{args.spec}: ok ({symbolic.name}: {len(symbolic.states)} states, "
          f"{len(symbolic.inputs)} inputs, {len(symbolic.outputs)} outputs, "
          f"{len(symbolic.parameters)} parameters; {n} warning{'s' if n != 1 else ''})")
    return 0


def _print_ranges(symbolic, data) -> None:
    """The range of every input and output as the fit reads it (after the data map's unit
    conversion, scale and offset), in the spec's units, with the column it comes from: a
    column read in the wrong unit shows here as a range 57 times too large or small."""
    import numpy as np

    from .data import load_record

    rec = load_record(symbolic, data)
    maps = {("input", c.name): c for c in symbolic.data.inputs}
    maps.update({("output", c.name): c for c in symbolic.data.outputs})
    print(f"ranges as read ({rec.n} samples, in the spec's units):")
    for kind, variables, arr in (("input", symbolic.inputs, rec.u), ("output", symbolic.outputs, rec.y)):
        for j, v in enumerate(variables):
            col = np.asarray(arr[:, j], float)
            fin = col[np.isfinite(col)]
            cm = maps.get((kind, v.name))
            src = "" if cm is None else (f"`{cm.column}`" if cm.column else f"expr of {', '.join(cm.columns)}")
            conv = "" if cm is None or not getattr(cm, "unit", None) else f", converted from {cm.unit}"
            scale = "" if cm is None or (cm.scale == 1.0 and cm.offset == 0.0) else \
                f", × {cm.scale:g} + {cm.offset:g}"
            rng = f"{fin.min():.6g} .. {fin.max():.6g}" if fin.size else "no finite value"
            print(printable(f"  {kind} {v.name}: {rng} {v.unit or ''} ({src}{conv}{scale})"))


def _fit_start(spec, symbolic):
    """``start(record)`` for :func:`vsidgen.data.check.check_record`: the state means a fit of
    ``spec`` starts from on that (already loaded) record (:attr:`vsidgen.estimator.Problem.measured_start`:
    directly measured states from their outputs, the others the outputs depend on solved
    from them). None when every state is an output as it stands (the check's own start is
    then the fit's): the model is only built when the start needs it."""
    states = {s.symbol for s in symbolic.states}
    if states <= set(symbolic.observations):
        return None

    def start(rec):
        import tempfile

        from .estimator import FitOptions, Problem
        from .model import load_model

        with tempfile.TemporaryDirectory() as td:
            model = load_model(spec, generated_dir=td)
        return Problem(model, [rec], FitOptions()).measured_start[0]

    return start


# ---- show --------------------------------------------------------------------

def _add_show(subparsers) -> None:
    p = subparsers.add_parser(
        "show", help="print the model equations",
        description="Print the model: states, inputs, outputs, parameters, definitions, "
                    "drift dx/dt = f(x, u, p) and outputs y = h(x, u, p), with units; then the "
                    "settings that change what is fitted: integrator, sub-steps, input hold and "
                    "delays, process noise (states, structure, estimate, floors, degenerate, "
                    "states without it) and measurement noise per output.")
    p.add_argument("spec", metavar="SPEC", help="spec file (YAML)")
    p.add_argument("--latex", action="store_true", help="print the equations as LaTeX")
    p.set_defaults(handler=_cmd_show)


def _unit(u) -> str:
    return f" [{u}]" if u else ""


def _cmd_show(args) -> int:
    import sympy

    from .spec import compile_spec

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
    # spec text is shown with non-printable characters escaped (no terminal control sequences)
    print(f"model {m.name}: {printable(m.description)}".rstrip(": "))
    for title, items in (("states", m.states), ("inputs", m.inputs), ("outputs", m.outputs)):
        print(f"{title}:")
        for v in items:
            print(f"  {v.name}{_unit(v.unit)}{'  ' + printable(v.description) if v.description else ''}")
    if m.constants:
        print("constants:")
        for c in m.constants:
            print(f"  {c.name} = {c.value:g}{_unit(c.unit)}"
                  f"{'  (' + printable(c.source) + ')' if c.source else ''}")
    if m.parameters:
        print("parameters:")
        for p in m.parameters:
            extra = []
            if p.lower is not None or p.upper is not None:
                extra.append(f"bounds [{p.lower}, {p.upper}]")
            if p.fixed:
                extra.append("fixed")
            print(f"  {p.name}{_unit(p.unit)} initial {p.initial:g}"
                  + (", " + ", ".join(extra) if extra else "")
                  + (f"  {printable(p.description)}" if p.description else ""))
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
    for line in _settings_lines(m):
        print(line)
    return 0


_HOLD = {"zoh": "zero-order hold (held over each sample)",
         "foh": "first-order hold (interpolated linearly between samples)"}


def _std_text(values: dict, unit_of) -> str:
    return ", ".join(f"{n} {v:g}{_unit(unit_of.get(n))}" for n, v in values.items())


def _settings_lines(m) -> list[str]:
    """What the fit uses besides the equations: integration, input hold and delays, noise."""
    lines = ["settings:",
             f"  integrator: {m.integrator}, {m.substeps} sub-step{'s' if m.substeps != 1 else ''} "
             f"per sample; inputs: {_HOLD.get(m.input_hold, m.input_hold)}"]
    delays = [f"{v.name} {v.delay:g} s" for v in m.inputs if getattr(v, "delay", 0.0)]
    lines.append(f"  input delay: {', '.join(delays)} (the model sees u(t - delay))" if delays
                 else "  input delay: none")
    pn = m.process_noise
    states = [v.name for v in m.states]
    noisy = [s for s in states if s in pn.states] if pn.states else list(states)
    if not pn.estimate:  # fixed in the spec: a state without a positive std has none
        noisy = [s for s in noisy if float(pn.std.get(s, 0.0) or 0.0) > 0]
    quiet = [s for s in states if s not in noisy]
    unit_of = {v.name: (f"{v.unit}/sqrt(s)" if v.unit else "1/sqrt(s)") for v in m.states}
    what = "estimated" if pn.estimate else "fixed"
    structure = {"diagonal": "diagonal G", "full": "full lower-triangular G, correlated"}.get(
        pn.structure, pn.structure)
    proc = (f"  process noise: {', '.join(noisy)} ({structure}, {what})" if noisy
            else "  process noise: none")
    lines.append(proc)
    if pn.std:
        lines.append(f"    {'initial std' if pn.estimate else 'std'}: {_std_text(dict(pn.std), unit_of)}")
    if any(float(v) > 0 for v in pn.floor.values()):
        lines.append(f"    floor: {_std_text({k: v for k, v in pn.floor.items() if float(v) > 0}, unit_of)}")
    if getattr(pn, "degenerate", ()):
        lines.append(f"    degenerate (no independent noise, G_ii = 0): {', '.join(pn.degenerate)}")
    if quiet:
        lines.append(f"    without process noise (fitted in the limit of vanishing noise): {', '.join(quiet)}")
    lines.append("  measurement noise:")
    out_unit = {v.name: v.unit for v in m.outputs}
    for mn in m.measurement_noise:
        parts = ["estimated" if mn.estimate else "fixed"]
        if mn.std is not None:
            parts.append(f"{'initial ' if mn.estimate else ''}std {mn.std:g}{_unit(out_unit.get(mn.output))}")
        fl = mn.floor
        parts.append("floor auto (data resolution / sqrt(12))" if fl == "auto"
                     else "no floor" if not fl else f"floor {float(fl):g}{_unit(out_unit.get(mn.output))}")
        lines.append(f"    {mn.output}: {', '.join(parts)}")
    return lines


# ---------------------------------------------------------------- simulate / fit / report

def _name_values(items, what):
    """Parse repeated NAME=VALUE options into a dict of floats."""
    out = {}
    for item in items or ():
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise VsidgenError(f"--{what} {item!r}: expected NAME=VALUE")
        try:
            x = float(value)
        except ValueError:
            raise VsidgenError(f"--{what} {item!r}: {value!r} is not a number") from None
        if not math.isfinite(x):
            raise VsidgenError(f"--{what} {item!r}: the value must be finite")
        if name.strip() in out and out[name.strip()] != x:
            # `--param MQ=5 --param MQ=6` kept the last one silently (session 46)
            raise VsidgenError(f"--{what} {name.strip()} is given twice, with different values "
                               f"({out[name.strip()]:g} and {x:g})")
        out[name.strip()] = x
    return out


def _check_names(given, known, what, model=None, option=None):
    from .suggest import suggest, unknown_name_error

    for name in given:
        if name not in known:
            if model is not None:
                raise unknown_name_error(name, what, model, option=option or f"--{what}")
            hint = suggest(name, known, role=what)
            hint = f" — {hint}" if hint else f" (known: {', '.join(known)})"
            raise VsidgenError(f"unknown {what} `{name}`{hint}")


def _add_simulate(sub):
    p = sub.add_parser(
        "simulate", help="simulate a spec and write a synthetic record (CSV)",
        description="Simulate the model of SPEC with process and measurement noise and write a "
                    "CSV record laid out like the spec's data mapping, so that `vsidgen fit` "
                    "reads it back. Inputs come from maneuver generators (--input) or from a "
                    "CSV record (--inputs-from).")
    p.add_argument("spec", help="model spec (YAML)")
    p.add_argument("-o", "--out", required=True, help="CSV file to write (atomically)")
    p.add_argument("--param", action="append", metavar="NAME=VALUE",
                   help="parameter value (repeatable; others take their spec initial value)")
    p.add_argument("--params-from", metavar="RESULTS_JSON",
                   help="take parameter values from a fit's results.json")
    p.add_argument("--input", action="append", metavar="NAME=MANEUVER[:OPT=V,...]",
                   help="input generator, e.g. de=3211:amplitude=0.02,start=1,unit=0.5 "
                        "(maneuvers: 3211, doublet, multisine, step, const)")
    p.add_argument("--inputs-from", metavar="CSV", help="read inputs (and time) from a record")
    p.add_argument("--duration", type=float, default=None, help="record length in s")
    p.add_argument("--dt", type=float, default=None, help="sample period in s")
    p.add_argument("--x0", action="append", metavar="NAME=VALUE", help="initial state")
    p.add_argument("--process-std", action="append", metavar="STATE=STD",
                   help="process-noise std in state-unit/sqrt(s)")
    p.add_argument("--measurement-std", action="append", metavar="OUTPUT=STD",
                   help="measurement-noise std in output units")
    p.add_argument("--quantize", action="append", metavar="OUTPUT=STEP",
                   help="quantize an output to a resolution step")
    p.add_argument("--integrator", choices=("euler", "rk4"), default=None)
    p.add_argument("--substeps", type=int, default=None)
    p.add_argument("--seed", type=_seed, default=0, help="random seed (0 to 2**32 - 1)")
    p.set_defaults(handler=_cmd_simulate)


def _cmd_simulate(args) -> int:
    import numpy as np

    from .atomic import check_output_file
    from .data import load_record
    from .errors import printable
    from .limits import check_input_file

    reads = [args.spec] + [p for p in (args.inputs_from, args.params_from) if p]
    if args.inputs_from:
        check_input_file(args.inputs_from, what="data file")
    if args.params_from:
        check_input_file(args.params_from, what="results file", kind="json", data_error=False)
    check_output_file(args.out, reads=reads)
    if args.substeps is not None and args.substeps < 1:
        raise VsidgenError(f"--substeps must be >= 1, got {args.substeps}")

    rec = None
    if args.inputs_from:
        from .spec import compile_spec

        rec = load_record(compile_spec(args.spec), args.inputs_from)

    # every NAME=VALUE option parsed (finite numbers) before the model is built
    given = _name_values(args.param, "param")
    x0 = _name_values(args.x0, "x0")
    pstd = _name_values(args.process_std, "process-std")
    mstd = _name_values(args.measurement_std, "measurement-std")
    quant = _name_values(args.quantize, "quantize")
    for what, values in (("process-std", pstd), ("measurement-std", mstd), ("quantize", quant)):
        for name, v in values.items():
            if v < 0 or (what == "quantize" and v == 0):
                raise VsidgenError(f"--{what} {name}={v:g}: the value must be "
                                   + ("> 0" if what == "quantize" else ">= 0"))

    enable_compilation_cache()
    from .model import load_model
    from .data.simulate import parse_input_spec, simulate_to_csv

    model = load_model(args.spec)
    theta = {}
    if args.params_from:
        theta.update(read_estimates(args.params_from, option="--params-from"))
        # named as the file's, not as a --param (the message named `--param NOPE`; session 46)
        _check_names(theta, model.parameter_names, "parameter", model,
                     f"--params-from {printable(args.params_from)}:")
    theta.update(given)
    _check_names(theta, model.parameter_names, "parameter", model, "--param")
    _check_names(x0, model.state_names, "state", model, "--x0")
    _check_names(pstd, model.state_names, "state", model, "--process-std")
    _check_names(mstd, model.output_names, "output", model, "--measurement-std")
    _check_names(quant, model.output_names, "output", model, "--quantize")
    if args.inputs_from:
        if args.input:
            raise VsidgenError("give either --input generators or --inputs-from, not both")
        # the record's uniform grid (fit reads the same time column the same way): stamps
        # with an epoch offset carry rounding jitter that t_raw - t_raw[0] would keep
        t, u = np.arange(rec.n) * rec.dt, rec.u
    else:
        dt = args.dt
        if dt is None or args.duration is None:
            raise VsidgenError("--duration and --dt are needed when inputs come from generators")
        if not (np.isfinite(dt) and np.isfinite(args.duration)) or dt <= 0 or args.duration <= dt:
            raise VsidgenError("--dt must be positive and smaller than --duration (both finite)")
        if args.duration / dt > 1e8:
            raise VsidgenError(f"--duration {args.duration:g} s at --dt {dt:g} s gives more than "
                               "1e8 samples; shorten the record or raise --dt")
        n = int(round(args.duration / dt)) + 1
        # the record written must be one `fit` reads: at most the data limit, at 24 bytes a
        # value (%.17g and a comma) in the time, input and output columns; 1e8 samples were
        # allowed and ended in MemoryError (session 44)
        from .limits import DATA_LIMIT_ENV, data_limit, human_bytes
        size = n * (1 + model.nu + model.ny) * 24
        if size > data_limit():
            raise VsidgenError(f"--duration {args.duration:g} s at --dt {dt:g} s gives {n} samples, "
                               f"a record of about {human_bytes(size)}: larger than the "
                               f"{human_bytes(data_limit())} that fit reads\n  hint: shorten the "
                               f"record, raise --dt, or raise ${DATA_LIMIT_ENV}")
        t = np.arange(n) * dt
        gens = {}
        for item in args.input or ():
            spec = parse_input_spec(item)
            if spec.name in gens:
                # the second replaced the first without a word (session 46)
                raise VsidgenError(f"--input {spec.name} is given twice\n  hint: give each input "
                                   "once; join maneuvers with '+' to add them up "
                                   f"({spec.name}=doublet:amplitude=0.02+step:amplitude=0.01)")
            gens[spec.name] = spec.evaluate
        _check_names(gens, model.input_names, "input", model, "--input")
        u = np.zeros((n, model.nu))
        for j, name in enumerate(model.input_names):
            if name in gens:
                u[:, j] = gens[name](t)
    x0v = np.array([x0.get(s, 0.0) for s in model.state_names])
    res = simulate_to_csv(model, args.out, theta=theta, t=t, u=u, x0=x0v, process_std=pstd,
                          measurement_std=mstd, integrator=args.integrator or model.integrator,
                          substeps=args.substeps or model.substeps, seed=args.seed,
                          quantize=quant or None)
    for note in res.warnings:
        eprint(f"warning: {note}")
    print(f"wrote {args.out} ({len(t)} samples, dt = {float(t[1] - t[0]):g} s)")
    return 0


def _add_fit(sub):
    p = sub.add_parser(
        "fit", help="estimate parameters and noise from flight records",
        description="Fit SPEC to one or more records (shared parameters, one smoother per "
                    "record) by maximising the evidence lower bound, from null initial guesses. "
                    "Writes DIR/results.json and DIR/signals_<record>.csv atomically: a failed "
                    "or interrupted fit leaves earlier results in DIR intact. Exit status 0 "
                    "when converged, 1 when the optimizer (or the validation smoothing) stopped without converging (results "
                    "are still written and say so), 2 on bad input.")
    p.add_argument("spec", help="model spec (YAML)")
    p.add_argument("data", nargs="+", help="estimation record(s) (CSV or MATLAB .mat)")
    p.add_argument("--validate", nargs="+", default=[], metavar="DATA",
                   help="validation record(s): θ fixed at the estimate, smoothing only")
    p.add_argument("-o", "--out", required=True, help="results directory")
    p.add_argument("--integrator", choices=("euler", "rk4"), default=None,
                   help="transition mean (default: the spec's; euler = the paper's Euler–Maruyama)")
    p.add_argument("--substeps", type=int, default=None, help="integration sub-steps per sample")
    p.add_argument("--optimizer", choices=("structured-newton", "trust-constr"),
                   default="structured-newton",
                   help="structured Newton (default) or the paper's scipy trust-constr")
    p.add_argument("--max-iter", type=int, default=200,
                   help="optimizer iterations per noise start (each start is a fit of its own; a stage of the deterministic limit of states without process noise gets max(30, MAX_ITER/4)) (default 200)")
    p.add_argument("--init-states", choices=("measured", "zero"), default="measured",
                   help="initial state-path mean: measured states where possible, or zero")
    p.add_argument("--noise-start", choices=("auto", "release", "data", "data-meas", "unit"), default="auto",
                   help="starting noise levels: from the data's sample-to-sample spread, or "
                        "std = 1 in SI units and rad ('unit', the paper's), or 'release' (unmeasured states with "
                        "process noise first held deterministic, then released); auto tries "
                        "them all and keeps the best converged one (θ always starts at the "
                        "spec's null guesses)")
    p.add_argument("--report", action="store_true", help="also write DIR/report.html")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty DIR that is not a vsidgen results directory "
                        "(only vsidgen's files are replaced; other files are kept)")
    p.add_argument("--reference", metavar="JSON[:METHOD]", default=None,
                   help="reference estimates to compare in the report")
    add_override_arguments(p)
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.set_defaults(handler=_cmd_fit)


def _cmd_fit(args) -> int:
    from .fitjob import run_fit

    if args.max_iter < 1:
        raise VsidgenError(f"--max-iter must be >= 1, got {args.max_iter}")
    if args.substeps is not None and args.substeps < 1:
        raise VsidgenError(f"--substeps must be >= 1, got {args.substeps}")
    enable_compilation_cache()

    overrides = overrides_of(args)
    from .progress import FitProgress

    progress = None if args.quiet else FitProgress(sys.stderr)
    try:
        job = run_fit(args.spec, args.data, out=args.out, validate=args.validate,
                      overrides=overrides,
                      integrator=args.integrator, substeps=args.substeps,
                      optimizer=args.optimizer, max_iter=args.max_iter,
                      init_states=args.init_states, noise_start=args.noise_start,
                      progress=progress,
                      report=args.report, reference=args.reference,
                      overwrite=args.overwrite)
    finally:
        if progress is not None:
            progress.close()
    res = job.results
    for w in res["warnings"][job.shown_before:]:    # the spec's were shown before the fit
        eprint(f"warning: {w['message']}")
    if not args.quiet:
        width = max(len(n) for n in res["parameters"]) if res["parameters"] else 4
        print(f"{'parameter':<{width}}  {'estimate':>13}  {'std error':>11}")
        for name, p in res["parameters"].items():
            se = "fixed" if p["fixed"] else (f"{p['std_error']:.4g}" if p["std_error"] is not None else "n/a")
            print(f"{name:<{width}}  {p['estimate']:>13.6g}  {se:>11}")
    if not args.quiet:
        _print_fit_quality(res)
    state = "" if res["converged"] else "NOT CONVERGED — "
    print(f"{state}{res['status']} ({res['iterations']} iterations, "
          f"{res['wall_time_s']:.1f} s); ELBO {res['elbo']:.6g}; results in {args.out}")
    det = res.get("deterministic_states") or []
    if det:
        lim = res.get("deterministic_limit") or {}
        how = ("exact limit of vanishing process noise" if lim.get("reached")
               else "limit of vanishing process noise NOT reached" if lim else "quasi-deterministic")
        print(f"states without process noise: {', '.join(det)} ({how})")
    lim = res.get("deterministic_limit") or {}
    degen = [x for x in lim.get("states") or () if x not in det]
    if degen:
        how = ("exact limit" if lim.get("reached") else "limit NOT reached")
        print(f"degenerate process noise: {', '.join(degen)} (no independent part: a combination "
              f"of the earlier states' noise sources, G_ii = 0; {how})")
    issues = res.get("std_error_issues") or []
    if res["parameters"] and not res.get("std_errors_reliable", True):
        codes = ", ".join(f"{i['code']}" + (f" ({', '.join(i['parameters'])})" if i.get("parameters") else "")
                          for i in issues) or "see warnings"
        print(f"standard errors: UNRELIABLE — {codes}")
    val = res.get("validation") or {}
    val_ok = val.get("converged", True) is not False
    if val.get("elbo") is not None:
        vstate = "converged" if val_ok else "NOT CONVERGED — " + str(val.get("status"))
        far = any(w.get("code") == "validation_elbo_far_below" for w in res["warnings"])
        print(f"validation smoothing: {vstate}; validation ELBO {val['elbo']:.6g}"
              + (" (FAR BELOW the estimation's per sample: see the warning)" if far else ""))
        if val.get("elbo_own_noise") is not None:
            trims = val.get("own_noise_free") or []
            print(f"validation ELBO at the validation records' own noise (θ fixed"
                  + (f" but the trim constants {', '.join(trims)}" if trims else "")
                  + f", noise re-estimated; compares models by their physics): "
                  f"{val['elbo_own_noise']:.6g}"
                  + ("" if val.get("own_noise_converged") else " (not converged)"))
    if job.report_error is not None:
        eprint(f"internal error: the report could not be written ({job.report_error}); the "
               f"fit's results are in {args.out}\n  hint: this is a bug in vsidgen; rerun "
               "with VSIDGEN_DEBUG=1 for the traceback and report it")
        return 3
    return 0 if res["converged"] and val_ok else 1


def _print_fit_quality(res) -> None:
    """Per record and output: NRMSE fit % (MATLAB ``compare``) of the free simulation and the
    one-step prediction, and RMS, Theil U and R² of the free simulation."""
    rows = []
    for kind in ("estimation", "validation"):
        for rec, m in ((res.get("metrics") or {}).get(kind) or {}).items():
            for o, sim in (m.get("simulation") or {}).items():
                pred = (m.get("prediction") or {}).get(o) or {}
                rows.append((f"{rec}{' (val.)' if kind == 'validation' else ''}", o, sim, pred))
    if not rows:
        return

    def f(x, fmt):
        return "n/a" if x is None or x != x else format(x, fmt)

    w = max(len(r[0]) for r in rows)
    wo = max(6, max(len(r[1]) for r in rows))
    print(f"{'record':<{w}}  {'output':<{wo}}  {'fit sim':>8}  {'fit pred':>8}  "
          f"{'RMS sim':>10}  {'Theil U':>7}  {'R2':>7}")
    for rec, o, sim, pred in rows:
        rec = printable(rec)                  # a record's name is its file's name
        print(f"{rec:<{w}}  {o:<{wo}}  {f(sim.get('fit_percent'), '7.1f') + '%':>8}  "
              f"{f(pred.get('fit_percent'), '7.1f') + '%':>8}  {f(sim.get('rms'), '10.4g'):>10}  "
              f"{f(sim.get('theil'), '7.3f'):>7}  {f(sim.get('r2'), '7.4f'):>7}")


def _add_report(sub):
    p = sub.add_parser("report", help="write DIR/report.html for a results directory",
                       description="Render a fit's results directory as one self-contained "
                                   "HTML file (figures embedded, no network needed).")
    p.add_argument("dir", help="results directory written by `vsidgen fit`")
    p.add_argument("--reference", metavar="JSON[:METHOD]", default=None,
                   help="reference estimates (e.g. ../shared/reference/hfb320_reference.json:fem)")
    p.add_argument("-o", "--out", default=None, help="HTML file (default DIR/report.html)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing HTML file that vsidgen did not write")
    p.set_defaults(handler=_cmd_report)


def _seed(text: str) -> int:
    """--seed: an integer numpy accepts (0 … 2**32 − 1); else a usage error (exit 2)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 0 <= v < 2 ** 32:
        raise argparse.ArgumentTypeError(f"{v} is outside 0 … 2**32 - 1")
    return v


def _cmd_report(args) -> int:
    """Write the report; never over a file it reads or a file of the user's.

    The default ``DIR/report.html`` may be replaced when DIR's manifest lists it
    (vsidgen wrote it); any other existing file needs ``--overwrite``
    (:func:`vsidgen.report.write_report` decides).
    """
    from .atomic import check_output_file
    from .report import parse_reference, write_report

    d = pathlib.Path(args.dir)
    out = pathlib.Path(args.out) if args.out is not None else d / "report.html"
    ref_path = parse_reference(args.reference)[2] if args.reference is not None else None
    reads = [d / "results.json"] + ([ref_path] if ref_path is not None else [])
    if d.is_dir():
        reads += [q for q in d.iterdir() if q.name.startswith("signals_")]
    check_output_file(out, reads=reads)
    try:       # (write_report refuses a file vsidgen did not write, unless --overwrite)
        path = write_report(args.dir, out=out, reference=args.reference,
                            overwrite=bool(args.overwrite))
    except (ValueError, TypeError, KeyError, IndexError, AttributeError, RecursionError) as err:
        # results.json parsed, but its content is not what vsidgen writes (hand-edited or
        # hostile: a 10^5-deep nesting, a 5000-digit integer, a ragged correlation matrix)
        raise VsidgenError(f"{d / 'results.json'}: error: its content is not what vsidgen "
                           f"writes ({type(err).__name__}: {str(err)[:200]})\n  hint: re-run "
                           "`vsidgen fit` to write it again") from None
    print(f"wrote {path}")
    return 0


def _add_diagnose(sub):
    from .discrepancy.search import add_diagnose_parser

    add_diagnose_parser(sub)


def _add_fleet(sub):
    from .fitjob import add_fleet_parser

    add_fleet_parser(sub)


#: subcommand registrars, in --help order (the coordinator appends simulate, fit, report, diagnose)
COMMANDS = [_add_build, _add_check, _add_show, _add_simulate, _add_fit, _add_report,
            _add_diagnose]
COMMANDS.append(_add_fleet)


#: commands whose arguments parse without the diagnose parser (which imports scipy.stats)
_LIGHT_COMMANDS = frozenset({"build", "check", "show", "simulate", "fit", "report"})


def make_parser(*, light: bool = False) -> argparse.ArgumentParser:
    """The argument parser; ``light`` lists ``diagnose`` without building its options
    (for argv naming another command: it starts about a second faster)."""
    parser = argparse.ArgumentParser(
        prog="vsidgen",
        description="Aircraft system identification from YAML model specs: compile specs to JAX, "
                    "fit them to flight records by variational maximum likelihood, report.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in COMMANDS:
        if light and add is _add_diagnose:
            sub.add_parser("diagnose", help="find, explain and add physics the model leaves out")
            continue
        add(sub)
    return parser


def _unrecognized(parser: argparse.ArgumentParser, args, extra: list[str]) -> int:
    """The command's usage and, for a mistyped option, the nearest of its own options
    (`--validation` printed the top-level usage and no hint; session 44). Exit status 2."""
    import difflib

    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    cmd = sub.choices.get(getattr(args, "command", None), parser)
    options = [o for a in cmd._actions for o in a.option_strings if o.startswith("--")]
    lines = [cmd.format_usage().rstrip(),
             f"{cmd.prog}: error: unrecognized argument{'s' if len(extra) > 1 else ''}: "
             + " ".join(extra)]
    for word in extra:
        if word.startswith("-"):
            near = difflib.get_close_matches(word.split("=", 1)[0], options, n=1, cutoff=0.6)
            if near:
                lines.append(f"  hint: did you mean `{near[0]}`? (`{cmd.prog} --help` lists "
                             "the options)")
    eprint("\n".join(lines))
    return 2


class _PrintableStdout:
    """``sys.stdout`` while a command runs: every line written is :func:`printable` (its
    line breaks kept), so a file name, a record's name or its error text with a terminal
    escape in it cannot reach the terminal through any of the commands' summary lines (red
    team, session 48: the fleet summary, `check`'s ok line, `report`'s and `simulate`'s
    "wrote" lines; stderr goes through :func:`eprint`)."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text) -> int:
        self._stream.write("\n".join(printable(line) for line in str(text).split("\n")))
        return len(text)

    def __getattr__(self, name):
        return getattr(self._stream, name)


def main(argv=None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 error, 130 interrupted)."""
    stdout = sys.stdout
    sys.stdout = _PrintableStdout(stdout)
    try:
        return _main(argv)
    finally:
        if isinstance(sys.stdout, _PrintableStdout):
            sys.stdout = stdout


def _main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = make_parser(light=bool(argv) and argv[0] in _LIGHT_COMMANDS)
    try:
        args, extra = parser.parse_known_args(argv)
        if extra:
            return _unrecognized(parser, args, extra)
    except SystemExit as exc:  # argparse: --help (0) or usage error (2)
        return int(exc.code or 0) if isinstance(exc.code, int) else 2
    try:
        return int(args.handler(args) or 0)
    except VsidgenError as err:
        eprint(str(err))
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # the file system refused: a file where a folder is written, a
        # device or /proc path, no permission, disk full — the user's environment, not a bug
        where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
        why = ("exists and is not a folder" if isinstance(exc, (FileExistsError, NotADirectoryError))
               else exc.strerror or str(exc))
        eprint(f"error: cannot write or read {where or 'a file'}: {why}\n"
               "  hint: choose an output folder you can write to, where no file stands in the "
               "way of the folders vsidgen creates (--out, ./generated)")
        return 2
    except Exception as exc:  # a bug in vsidgen, not in the user's input
        import os
        import traceback

        if os.environ.get("VSIDGEN_DEBUG"):
            traceback.print_exc()
        eprint(f"internal error: {type(exc).__name__}: {exc}\n  hint: this is a bug in "
               "vsidgen; rerun with VSIDGEN_DEBUG=1 for the traceback and report it")
        return 3


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
