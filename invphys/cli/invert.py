"""``invphys invert BUNDLE``: answer a target with material parameters."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from invphys.cli.common import console, emit, escape, handle_errors, out_console
from invphys.core.errors import InvphysError


def register(app: typer.Typer) -> None:
    app.command("invert")(invert)


def _options(items: list[str]) -> dict[str, Any]:
    """``--sim-option key=value`` items as a dict (values parsed as YAML scalars: 1, 0.5, true, cpu)."""
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise InvphysError(f"--sim-option {item!r}: expected key=value")
        try:
            out[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError:
            out[key.strip()] = value
    return out


@handle_errors
def invert(
    bundle: Path = typer.Argument(..., help="inverter bundle directory (e.g. inverters/orange_peel_paper)"),
    target: str | None = typer.Option(None, "--target", "-t", help="JSON, YAML or CSV file of one or many targets"),
    feature: list[str] = typer.Option(None, "--feature", "-f", help="NAME=VALUE of one target feature (repeat)"),
    observed: list[str] = typer.Option(None, "--observed", help="saved trajectory (.npz or run directory)"),
    partial: bool = typer.Option(False, "--partial", help="allow missing features (left out of R)"),
    method: str | None = typer.Option(None, "--method", "-m", help="bundle method or installed optimiser"),
    top_k: int = typer.Option(1, "--top-k", "-k", min=1, help="diverse candidates per target"),
    refine: int = typer.Option(0, "--refine", min=0, help="CMA-ES surrogate evaluations refining each candidate"),
    workers: int = typer.Option(0, "--workers", min=0, max=256, help="answer in N processes (hundreds of targets)"),
    validate: bool = typer.Option(False, "--validate", help="re-run the simulator on the answers (R_actual)"),
    sim_option: list[str] = typer.Option(None, "--sim-option", help="simulator KEY=VALUE for --validate/--polish"),
    sim_batch: int = typer.Option(16, "--sim-batch", min=1,
                                  help="rows per simulator call for --validate and --polish (on a GPU: 64-200)"),
    validate_workers: int = typer.Option(0, "--validate-workers", min=0, max=256, help="feature extractors in parallel"),
    polish: int | None = typer.Option(None, "--polish", help="N CMA-ES runs per target on the simulator (+validate)"),
    polish_below: float | None = typer.Option(None, "--polish-below", help="only targets with R_actual below R"),
    polish_sigma: float | None = typer.Option(None, "--polish-sigma", help="step in the [0, 1] cube (default 0.012)"),
    polish_popsize: int | None = typer.Option(None, "--polish-popsize", help="points per generation (default 8)"),
    polish_log: Path | None = typer.Option(None, "--polish-log", help="log of the runs: a stopped polish resumes"),
    polish_confirm: int | None = typer.Option(
        None, "--polish-confirm", help="re-simulate each target's best candidates K times after the polish and "
        "answer with the best mean R (the polish's R is a best-of-N run; default 0: off)"),
    polish_confirm_candidates: int | None = typer.Option(
        None, "--polish-confirm-candidates", help="candidates per target that --polish-confirm re-simulates "
        "(default 4; cost: candidates x K runs per target)"),
    sim_refine: int | None = typer.Option(None, "--sim-refine", help="N simulator runs per target refining answers"),
    sim_refine_starts: int = typer.Option(4, "--sim-refine-starts", min=1,
                                          help="candidates per target that --sim-refine starts from (default 4)"),
    sim_refine_popsize: int | None = typer.Option(None, "--sim-refine-popsize", help="points per batch (default 8)"),
    sim_refine_sigma: float | None = typer.Option(None, "--sim-refine-sigma", help="cma step (default 0.012)"),
    sim_refine_log: Path | None = typer.Option(None, "--sim-refine-log", help="log of the runs: a re-run resumes"),
    sim_refine_workers: int | None = typer.Option(None, "--sim-refine-workers", help="feature-extraction processes (0)"),
    sim_refine_strategy: str | None = typer.Option(None, "--sim-refine-strategy", help="corrected (the surrogate "
                                                   "corrected by the target's runs; default) or cma (CMA-ES)"),
    sim_refine_known: int | None = typer.Option(None, "--sim-refine-known", help="stored training rows that fit "
                                                "the target best, as starts at no run (default: 8 corrected, 0 cma)"),
    sim_refine_stop: float | None = typer.Option(None, "--sim-refine-stop", help="a target stops at this R_actual (0.98)"),
    sim_refine_patience: int | None = typer.Option(None, "--sim-refine-patience", help="stop once N runs gain < min gain"),
    sim_refine_min_gain: float | None = typer.Option(None, "--sim-refine-min-gain", help="the patience's gain (0.01)"),
    sim_refine_cost: float | None = typer.Option(None, "--sim-refine-cost", help="most estimated simulator time "
                                                 "per target, in average runs (default: N of --sim-refine; 0: off)"),
    seed: int = typer.Option(0, "--seed", help="seed of every random draw (with the target and the method it "
                             "decides the answer; a target's position in the file does not)"),
    level: float = typer.Option(0.9, "--level", help="level of the central intervals (posterior methods)"),
    samples: int | None = typer.Option(None, "--samples", help="posterior draws per target to save "
                                       "(needs --samples-out)"),
    samples_out: Path | None = typer.Option(None, "--samples-out", help="new .npz or .csv file for the draws"),
    plot: Path | None = typer.Option(None, "--plot", help="new .png/.pdf/.svg file: pairplot of the draws with the "
                                     "answer marked (several targets: one file each, numbered)"),
    csv_out: Path | None = typer.Option(None, "--csv", help="new .csv file: one row per target (answer, "
                                        "intervals, identifiability)"),
    allow_mismatch: bool = typer.Option(False, "--allow-mismatch",
                                        help="load a bundle made with another simulator version"),
    as_json: bool = typer.Option(False, "--json", help="machine-readable output on stdout"),
) -> None:
    """Answer targets (features by name) with material parameters from a trained inverter bundle."""
    from invphys.inverter.inverter import INTERVAL_DRAWS
    from invphys.inverter.seeds import check_seed
    from invphys.inverter.uncertainty import check_level

    check_seed(seed), check_level(level)
    polish_settings = _polish_settings(polish, polish_below, polish_sigma, polish_popsize, polish_log,
                                       polish_confirm, polish_confirm_candidates)
    refine_settings = _refine_settings(sim_refine, sim_refine_popsize, sim_refine_sigma, sim_refine_log,
                                       sim_refine_workers, sim_refine_strategy, sim_refine_known, sim_refine_stop)
    refine_settings.update(_stop_settings(sim_refine, sim_refine_patience, sim_refine_min_gain, sim_refine_cost))
    files = _output_files(samples, samples_out, plot, csv_out)
    inv, targets = _load(bundle, allow_mismatch, target, feature or [], observed or [], partial)
    top_k = max(top_k, sim_refine_starts) if refine_settings else top_k
    results = _answer(inv, targets, dict(method=method, top_k=top_k, refine=refine, seed=seed, level=level,
                                         draws=max(samples or 0, INTERVAL_DRAWS), workers=workers))
    _check_results(results, samples)
    records = _simulate(inv, results, sim_option or [], seed, sim_batch, validate, polish_settings, refine_settings,
                        validate_workers)
    _write_files(results, samples, files)
    _emit_results(bundle, results, records, seed, level, as_json)


def _load(bundle: Path, allow_mismatch: bool, target: str | None, feature: list[str], observed: list[str],
          partial: bool) -> tuple[Any, Any]:
    """The bundle's inverter and the targets; its load notes printed as warnings once the targets are read
    (a bad target: its one error line only)."""
    from invphys.inverter import load_inverter
    from invphys.inverter.target_input import cli_targets

    inv = load_inverter(bundle, strict=not allow_mismatch)
    targets = cli_targets(inv, target, feature, observed, partial)
    for note in inv.notes:
        console.print(f"[yellow]warning:[/] {escape(note)}", soft_wrap=True)
    return inv, targets


def _answer(inv: Any, targets: Any, options: dict[str, Any]) -> list[Any]:
    """``inv.invert_many(targets, **options)``, with a progress bar (stderr) for more than one target."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    if len(targets) < 2:
        return list(inv.invert_many(targets, **options))
    with Progress(TextColumn("answering"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=False) as bar:
        task = bar.add_task("answering", total=len(targets))
        return list(inv.invert_many(targets, on_answer=lambda n: bar.advance(task, n), **options))


def _check_results(results: list[Any], samples: int | None) -> None:
    """Refuse ``--samples`` for a method without draws; print each target's warnings."""
    if samples and not results[0].parameter_uncertainty.has_draws:
        raise InvphysError(f"--samples: method {results[0].method!r} has no posterior draws "
                           f"(posterior: {results[0].posterior})")
    for r in results:
        for w in r.warnings:
            console.print(f"[yellow]warning:[/] target {escape(r.label)}: {escape(w)}", soft_wrap=True)


def _simulate(inv: Any, results: list[Any], sim_option: list[str], seed: int, sim_batch: int, validate: bool,
              polish_settings: dict[str, Any], refine_settings: dict[str, Any], validate_workers: int = 0
              ) -> list[dict[str, Any]]:
    """``--validate``, ``--polish`` and ``--sim-refine`` on the simulator, in that order; the refine records."""
    overrides = _options(sim_option)
    if validate or polish_settings:
        _validate(inv, results, overrides, sim_batch, validate_workers)
    if polish_settings:
        _polish(inv, results, overrides, seed, batch_size=sim_batch, **polish_settings)
    return _sim_refine(inv, results, overrides, seed, sim_batch, **refine_settings) if refine_settings else []


def _emit_results(bundle: Path, results: list[Any], records: list[dict[str, Any]], seed: int, level: float,
                  as_json: bool) -> None:
    """The answers (with their refine records) as JSON or tables."""
    dicts = [r.to_dict() for r in results]
    for d, rec in zip(dicts, records, strict=False):
        d["sim_refine"] = rec
    data = {"bundle": str(bundle), "method": results[0].method, "seed": seed, "level": level, "results": dicts}

    def render(_: Any) -> None:
        for r in results:
            _render(r)

    emit(data, as_json, render)


def _validate(inv: Any, results: list[Any], overrides: dict[str, Any], batch_size: int = 16,
              extract_workers: int = 0) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    total = sum(len(r.candidates) for r in results)
    with Progress(TextColumn("validating"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=False) as bar:
        task = bar.add_task("validating", total=total)
        inv.validate(results, overrides=overrides, batch_size=batch_size, on_run=lambda _i: bar.advance(task),
                     extract_workers=extract_workers)


_POLISH_NAMES = {"budget": "--polish", "below": "--polish-below", "sigma0": "--polish-sigma",
                 "popsize": "--polish-popsize", "confirm": "--polish-confirm",
                 "confirm_candidates": "--polish-confirm-candidates"}


def _polish_settings(budget: int | None, below: float | None, sigma: float | None, popsize: int | None,
                     log: Path | None, confirm: int | None = None, candidates: int | None = None) -> dict[str, Any]:
    """The ``--polish*`` options as :meth:`Inverter.polish` arguments ({} without ``--polish``), checked
    by the inverter's :class:`~invphys.inverter.settings.PolishSettings`; the log before anything runs."""
    from invphys.inverter.settings import PolishSettings

    if budget is None:
        given = [n for n, v in (("--polish-below", below), ("--polish-sigma", sigma), ("--polish-popsize", popsize),
                                ("--polish-log", log), ("--polish-confirm", confirm),
                                ("--polish-confirm-candidates", candidates)) if v is not None]
        if given:
            raise InvphysError(f"{', '.join(given)} needs --polish N (simulator runs per target)")
        return {}
    if candidates is not None and not confirm:
        raise InvphysError("--polish-confirm-candidates needs --polish-confirm K (re-runs per candidate)")
    settings = PolishSettings.checked(names=_POLISH_NAMES, budget=budget, below=below, sigma0=sigma, popsize=popsize,
                                      confirm=confirm, confirm_candidates=candidates)
    if log is not None:
        from invphys.evaluators.polish import check_polish_log

        check_polish_log(log)
    return {"settings": settings, "log": log}


def _output_files(samples: int | None, samples_out: Path | None, plot: Path | None, csv_out: Path | None
                  ) -> dict[str, Path]:
    """The files asked for, checked before anything is computed (new files in existing folders)."""
    from invphys.inverter.output import check_new_file

    if samples is not None and not 1 <= samples <= 100_000:
        raise InvphysError(f"--samples must be in 1 .. 100000 draws per target, got {samples}")
    if (samples is None) != (samples_out is None):
        raise InvphysError("--samples N and --samples-out FILE go together (the draws are saved to FILE)")
    files = {}
    if samples_out is not None:
        files["samples"] = check_new_file(samples_out, "--samples-out", (".npz", ".csv"))
    if plot is not None:
        files["plot"] = check_new_file(plot, "--plot", (".png", ".pdf", ".svg"))
    if csv_out is not None:
        files["csv"] = check_new_file(csv_out, "--csv", (".csv",))
    return files


def _write_files(results: list[Any], samples: int | None, files: dict[str, Path]) -> None:
    from invphys.inverter.output import check_new_file, pairplot, write_samples, write_table

    if "samples" in files and samples:
        console.print(f"draws: {escape(str(write_samples(results, samples, files['samples'])))}", soft_wrap=True)
    if "csv" in files:
        console.print(f"table: {escape(str(write_table(results, files['csv'])))}", soft_wrap=True)
    if "plot" in files:
        p = files["plot"]
        paths = [p] if len(results) == 1 else [check_new_file(p.with_name(f"{p.stem}-{i + 1}{p.suffix}"), "--plot",
                                                              (p.suffix.lower(),)) for i in range(len(results))]
        for r, path in zip(results, paths, strict=True):
            console.print(f"pairplot: {escape(str(pairplot(r, path)))}", soft_wrap=True)


def _polish(inv: Any, results: list[Any], overrides: dict[str, Any], seed: int, **settings: Any) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    ps = settings["settings"]
    below = ps.below
    starts = [max((c.r_actual for c in r.candidates if c.r_actual is not None and c.r_actual == c.r_actual),
                  default=float("nan")) for r in results]
    total = sum(ps.budget for r0 in starts if not r0 >= below)
    if ps.confirm:  # at most: every candidate of a polished target, the answer of the others
        total += ps.confirm * sum(ps.confirm_candidates if not r0 >= below and ps.budget else 1 for r0 in starts)
    with Progress(TextColumn("polishing"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=False) as bar:
        task = bar.add_task("polishing", total=total)
        inv.polish(results, overrides=overrides, seed=seed, on_batch=lambda runs, _replayed: bar.advance(task, runs),
                   **settings)
        bar.update(task, completed=total)
    for r in results:
        p = r.polish
        if not p["polished"]:
            why = "--polish 0" if ps.budget == 0 else f"R_actual >= {below:g}"
            console.print(f"polish {escape(r.label)}: R_actual {_r(p['start_r_actual'])}, not polished ({why})",
                          soft_wrap=True)
            continue
        if "confirm" in p:
            c = p["confirm"]
            runs = p["runs"] - c["runs"]
            console.print(f"polish {escape(r.label)}: R_actual {_r(p['start_r_actual'])} -> "
                          f"{_r(_none_nan(c['r_selected']))} ({runs} simulator runs, best of them)", soft_wrap=True)
        else:
            console.print(f"polish {escape(r.label)}: R_actual {_r(p['start_r_actual'])} -> {_r(p['r_actual'])} "
                          f"({p['runs']} simulator runs{'' if p['improved'] else ', start kept'})", soft_wrap=True)
    for r in results:
        c = r.polish.get("confirm")
        if c is None:
            continue
        if c["pick"] < 0:
            console.print(f"confirm {escape(r.label)}: nothing simulated successfully to confirm", soft_wrap=True)
            continue
        console.print(f"confirm {escape(r.label)}: R_actual {_r(_none_nan(c['r_selected']))} (best of N) -> "
                      f"{_r(_none_nan(c['r_confirmed']))} (mean of {c['repeats']} re-runs; candidate "
                      f"{c['pick'] + 1} of {c['candidates']}{', answer changed' if c['changed'] else ''}; "
                      f"{c['runs']} simulator runs)", soft_wrap=True)
    call = results[0].polish["call"] if results else {}
    if call.get("replayed_runs"):
        console.print(f"polish: {call['replayed_runs']} of {call['runs']} runs replayed from {escape(str(call['log']))}",
                      soft_wrap=True)


def _refine_settings(budget: int | None, popsize: int | None, sigma: float | None, log: Path | None,
                     workers: int | None = None, strategy: str | None = None, known: int | None = None,
                     stop: float | None = None) -> dict[str, Any]:
    """The ``--sim-refine*`` options ({} without ``--sim-refine``), checked before anything runs."""
    from invphys.inverter.refine import REFINE_POPSIZE, REFINE_SIGMA0, REFINE_STOP, REFINE_STRATEGIES

    if budget is None:
        given = [n for n, v in (("--sim-refine-popsize", popsize), ("--sim-refine-sigma", sigma),
                                ("--sim-refine-log", log), ("--sim-refine-workers", workers),
                                ("--sim-refine-strategy", strategy), ("--sim-refine-known", known),
                                ("--sim-refine-stop", stop)) if v is not None]
        if given:
            raise InvphysError(f"{', '.join(given)} needs --sim-refine N (simulator runs per target)")
        return {}
    if not 1 <= budget <= 100_000:
        raise InvphysError(f"--sim-refine must be in 1 .. 100000 simulator runs per target, got {budget}")
    if popsize is not None and not 2 <= popsize <= 10_000:
        raise InvphysError(f"--sim-refine-popsize must be in 2 .. 10000, got {popsize}")
    if sigma is not None and not 0 < sigma <= 10:
        raise InvphysError(f"--sim-refine-sigma must be in (0, 10], got {sigma}")
    if workers is not None and not 0 <= workers <= 256:
        raise InvphysError(f"--sim-refine-workers must be in 0 .. 256, got {workers}")
    if strategy is not None and strategy not in REFINE_STRATEGIES:
        raise InvphysError(f"--sim-refine-strategy must be one of {', '.join(REFINE_STRATEGIES)}, got {strategy!r}")
    if known is not None and not 0 <= known <= 10_000:
        raise InvphysError(f"--sim-refine-known must be in 0 .. 10000, got {known}")
    if stop is not None and not 0 <= stop <= 1:
        raise InvphysError(f"--sim-refine-stop must be an R_actual in [0, 1] (0 or 1: never stop), got {stop}")
    if log is not None:
        from invphys.evaluators.refine_log import RunLog

        RunLog(log, key=None)  # the file and its place, before anything runs (what it was made for: on use)
    return {"budget": budget, "popsize": popsize or REFINE_POPSIZE, "sigma0": sigma or REFINE_SIGMA0, "log": log,
            "extract_workers": workers or 0, "strategy": strategy or REFINE_STRATEGIES[0], "known_starts": known,
            "stop": REFINE_STOP if stop is None else stop}


def _stop_settings(budget: int | None, patience: int | None, min_gain: float | None, cost: float | None = None
                    ) -> dict[str, Any]:
    """``--sim-refine-patience``, ``--sim-refine-min-gain`` and ``--sim-refine-cost`` as refine's ``patience``,
    ``min_gain`` and ``cost_budget`` (default: the run budget, where the simulator estimates run costs)."""
    from invphys.inverter.refine import REFINE_MIN_GAIN

    given = [n for n, v in (("--sim-refine-patience", patience), ("--sim-refine-min-gain", min_gain),
                            ("--sim-refine-cost", cost)) if v is not None]
    if budget is None and given:
        raise InvphysError(f"{', '.join(given)} needs --sim-refine N (simulator runs per target)")
    if min_gain is not None and patience is None:
        raise InvphysError("--sim-refine-min-gain needs --sim-refine-patience N (runs)")
    if patience is not None and not 1 <= patience <= 100_000:
        raise InvphysError(f"--sim-refine-patience must be in 1 .. 100000 runs, got {patience}")
    if min_gain is not None and not 0 <= min_gain <= 1:
        raise InvphysError(f"--sim-refine-min-gain must be an R_actual gain in [0, 1], got {min_gain}")
    if budget is None:
        return {}
    if cost is not None and not 0 <= cost <= 1e9:
        raise InvphysError(f"--sim-refine-cost must be a number of average runs in 0 .. 1e9 (0: off), got {cost}")
    out: dict[str, Any] = {"cost_budget": "budget" if cost is None else (cost or None)}
    if patience is not None:
        out.update(patience=patience, min_gain=REFINE_MIN_GAIN if min_gain is None else min_gain)
    return out


def _sim_refine(inv: Any, results: list[Any], overrides: dict[str, Any], seed: int, batch_size: int,
                **settings: Any) -> list[dict[str, Any]]:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from invphys.inverter.refine import refine

    total = settings["budget"] * len(results)
    with Progress(TextColumn("refining"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=False) as bar:
        task = bar.add_task("refining", total=total)
        records = refine(inv, results, overrides=overrides, seed=seed, batch_size=batch_size,
                         on_run=lambda runs, _replayed: bar.advance(task, runs), **settings)
        bar.update(task, completed=total)
    for r, rec in zip(results, records, strict=True):
        console.print(f"refine {escape(r.label)}: R_actual {_r(_none_nan(rec['start_r_actual']))} "
                      f"({escape(rec['start_source'])}) -> {_r(_none_nan(rec['r_actual']))} ({rec['runs']} simulator runs, {rec['simulator_s']:.1f} "
                      f"simulator-s{', stopped at the stop R' if rec['stopped'] else ''}"
                      f"{', stopped: stalled' if rec.get('stalled') else ''}"
                      f"{', stopped: cost budget spent' if rec.get('capped') else ''}"
                      f"{'' if rec['improved'] else ', start kept'})", soft_wrap=True)
    for r, rec in zip(results, records, strict=True):  # the refine's warnings (the others were printed before it)
        if rec.get("warning"):
            console.print(f"[yellow]warning:[/] target {escape(r.label)}: {escape(rec['warning'])}", soft_wrap=True)
    call = records[0]["call"] if records else {}
    if call.get("replayed_runs"):
        console.print(f"refine: {call['replayed_runs']} of {call['runs']} runs replayed from {escape(str(call['log']))}",
                      soft_wrap=True)
    return records


def _none_nan(value: float | None) -> float:
    return float("nan") if value is None else value


def _r(value: float) -> str:
    return "failed" if value != value else f"{value:.3f}"


def _render(result: Any) -> None:
    from rich.table import Table

    d = result.to_dict()
    out_console.print(f"[bold]target {escape(d['target'])}[/] - method {escape(d['method'])}, "
                      f"{d['evaluations']} surrogate evaluations, {d['wall_time_s'] * 1e3:.1f} ms")
    for c in d["candidates"]:
        head = f"candidate {c['rank']} ({escape(c['source'])}): R_surr {c['r_surrogate']:.3f}"
        if c.get("r_known") is not None:
            head += f", R_known {c['r_known']:.3f} (a stored row: its real features)"
        if "r_actual" in c:
            head += (f", R_actual {c['r_actual']:.3f}, gap {c['gap']:+.3f}" if c["r_actual"] is not None
                     else f", validation failed: {escape(str(c.get('failure')))}")
        out_console.print(head)
        out_console.print(_parameter_table(d, c))
        feats = Table("feature", "target", "predicted", "± std", "unit", *(["actual"] if "r_actual" in c else []))
        for name, f in c["features"].items():
            noise = f" ± {f['target_std']:.2g}" if f.get("target_std") else ""
            row = [name, "-" if f["target"] is None else f"{f['target']:.5g}{noise}", f"{f['predicted']:.5g}",
                   f"{f['std']:.2g}", f["unit"]]
            if "r_actual" in c:
                row.append("-" if f.get("actual") is None else f"{f['actual']:.5g}")
            feats.add_row(*row)
        out_console.print(feats)
    _uncertainty_line(d)
    if "spread" in d:
        wide = [k for k, v in d["spread"].items() if v > 0.25]
        if wide:
            out_console.print(f"candidates disagree on (normalised spread > 0.25): {', '.join(wide)}")


def _parameter_table(d: dict[str, Any], c: dict[str, Any]) -> Any:
    """The candidate's parameters; for the answer (rank 1) with draws, their interval and marks."""
    from rich.table import Table

    block = d.get("posterior") or d.get("neighbours") if c["rank"] == 1 else None
    if not block:
        params = Table("parameter", "value", "unit")
        for name, p in c["parameters"].items():
            params.add_row(name, f"{p['value']:.5g}", p["unit"] or "-")
        return params
    pct = f"{block['level']:.0%}"
    cols = ["parameter", "value", "median", f"{pct} low", f"{pct} high", "unit"]
    posterior = "posterior" in d and d["posterior"] is not None
    table = Table(*cols, *(["identified"] if posterior else []))
    for name, p in c["parameters"].items():
        b = block["parameters"][name]
        mark = [] if not posterior else ["yes" if b.get("identified") else "[yellow]no[/]"]
        value = f"{p['value']:.5g}" + (" [yellow](bound)[/]" if name in d.get("at_bound", []) else "")
        table.add_row(name, value, f"{b['median']:.5g}", f"{b['low']:.5g}", f"{b['high']:.5g}", p["unit"] or "-", *mark)
    return table


def _uncertainty_line(d: dict[str, Any]) -> None:
    post, noise = d.get("posterior"), d.get("noise")
    if noise:
        given = ", ".join(f"{escape(k)} ± {v:.3g}" for k, v in noise["std"].items() if v)
        how = "the posterior accounts for it" if noise["posterior"] else "this method's answer ignores it"
        out_console.print(f"noise assumed: {given or 'none (exact)'} (independent Gaussian; {how}); chi2 {noise['chi2']:.2f}")
    if post is not None and noise and noise["posterior"]:
        out_console.print(f"posterior: {post['draws']} draws of the noisy posterior under the surrogate "
                          f"(sequential Monte Carlo)")
    elif post is not None:
        out_console.print(f"posterior: {post['draws']} draws in the parameter box "
                          f"({post['outside_fraction']:.0%} of raw draws fell outside and were rejected"
                          f"{'; ' + str(post['clipped']) + ' clipped' if post['clipped'] else ''})")
    elif "neighbours" in d:
        out_console.print(f"posterior: none; the interval columns are the spread of {escape(d['neighbours']['note'])}")
    else:
        out_console.print(f"posterior: none ({escape(d.get('uncertainty', {}).get('note', ''))})")
