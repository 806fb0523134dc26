"""Nominal fit, then forward selection of candidate terms scored on check/.

Round 1 fits every term of the library on top of the nominal model; each later round adds, on top
of the terms selected so far, the most promising remaining ones. Every round also refits a
reference (the current model with the same budget) so a candidate is only credited for what its
physics adds, not for the extra optimisation.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from concurrent.futures import as_completed
from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm

from deform.diagnose.checked_fit import CheckErrors, Member, fit_and_check
from deform.diagnose.fitting import FitBudget, laplace_uncertainty
from deform.diagnose.localize import localize, short_rollout_residuals
from deform.diagnose.pool import FitPool, Job, fit_together_job, nominal_fits_job
from deform.diagnose.scoring import Score, bootstrap_ci, choose, nameable, penalised, score
from deform.diagnose.simulator import (
    CHECK_HORIZON,
    MATERIAL_DAMPING_MAX,
    MAX_STEP_S,
    Nominal,
    Simulator,
    arclength_of,
)
from deform.diagnose.spec import Inputs
from deform.diagnose.stack import groups_of
from deform.terms.library import LIBRARY, Term, beyond_material_level, make_term


@dataclass
class DiagnoseBudget:
    nominal_iterations: int = 60
    candidate: FitBudget = field(default_factory=FitBudget)
    max_rounds: int = 3
    later_round_candidates: int = 4
    localization_recordings: int = 6
    candidates: tuple[str, ...] = tuple(LIBRARY)
    progress: bool = True
    # slow terms (Term.slow) and their own reference fitted on windows growing to the one-second
    # scoring windows (FitBudget.final_horizon); off: every fit on the candidate budget's windows
    # (tool v6). On by default from tool v7: PyElastica 42/48 named first against 41/48, gap closed
    # 76 % against 72 %; own simulator 22/27 and controls unchanged (docs/diagnose.md)
    grow_slow_terms: bool = True
    # terms that live in the material frame (rest curvature) read each recording's roll about the
    # grippers from its first 0.2 s (Simulator.initial_roll); off: the "up" convention's roll in
    # every recording (tool v7). On from tool v8 (docs/diagnose.md)
    read_roll: bool = True
    # the nominal model fits how far past the gripped markers the grippers hold the rope
    # (Simulator: ``clamped``); off: the rope is freed at the markers (tool v8). On from tool v9:
    # the held-out PyElastica controls' false stiffness variations came from it (docs/diagnose.md)
    fit_clamp: bool = True
    # the clamp length [m] the nominal fit starts from (fit_clamp) or holds (not fit_clamp): a user
    # who knows how far past the gripped markers the jaws hold the rope gives it (deform diagnose
    # --clamp); 0 with fit_clamp off frees the rope at the markers
    clamp_m: float = 0.0
    # a number: slow terms (Term.slow: internal damping) and their reference fitted with the model
    # stepped at most this long [s], and every later round once one is selected; None: every fit at
    # simulator.MAX_STEP_S (10 ms, tool v10). At 5 ms the 10 ms step's own dissipation no longer
    # hides a light rope's damping (docs/diagnose.md)
    slow_step_s: float | None = 0.005
    # with slow_step_s: in round 1 the slow terms and their reference start from a nominal model
    # fitted at that step of its own (from tool v12); off: from the 10 ms nominal fit (fits v11, a
    # study), whose damping holds what the 10 ms step does not dissipate itself, so that at 5 ms
    # the internal damping made up the difference on an own-simulator control (+6.0 %)
    fine_nominal: bool = True

    @classmethod
    def quick(cls, progress: bool = True) -> DiagnoseBudget:
        """About a third of the default's work: the budget of the planted benchmark, on which the
        significance threshold was calibrated (docs/diagnose.md)."""
        return cls(
            nominal_iterations=40,
            candidate=FitBudget(iterations=25, batch=12, horizon=25),
            max_rounds=2,
            later_round_candidates=3,
            progress=progress,
        )


@dataclass
class FittedCandidate:
    """One candidate of a selection round: the term fitted on top of the current model, the fitted
    simulator, its check errors, its score against ``reference`` (the current model refitted with
    the same ``budget``, one-second window errors per check recording)."""

    name: str
    term: Term
    sim: Simulator
    checked: CheckErrors
    score: Score
    reference: np.ndarray
    budget: FitBudget
    nameable: bool  # by the tool's rule (deform.diagnose.scoring.nameable)
    base: Nominal  # the nominal parameters the fit started from


@dataclass
class Diagnosis:
    report: dict
    nominal_sim: Simulator
    final_sim: Simulator
    residuals: dict


def _nominal_from_model(path: str) -> Nominal:
    from deform.model import DeformModel

    m = DeformModel.load(path)
    return Nominal(
        float(m.log_beta.exp().mean()),
        float(m.log_gamma.exp().mean()),
        min(float(m.damping), MATERIAL_DAMPING_MAX),
    )


def contact_height(loc: dict) -> float | None:
    """The height below which localisation found errors growing (a plane the rod may touch), if any.

    Args:
        loc: from :func:`deform.diagnose.localize.localize`.

    Returns:
        The height [m], or None.
    """
    h = loc.get("by_height") or {}
    return h.get("low_threshold") if h.get("low_vs_rest_ratio", 0.0) > 1.5 else None


def equivalence_class(
    name: str, e_win, e_ref, others: list[tuple[str, object]], confidence: float = 0.90
) -> dict:
    """The nameable candidates that marker motion cannot tell apart from the chosen one.

    Per check recording, the difference of relative errors ``(e_other - e_win) / e_ref``; if its
    bootstrap interval over recordings holds 0, the two explanations fit the held-out data equally
    well and the report names both (an identifiability statement, not a choice by noise).
    -> {"equivalence_class": [name, ...], "equivalence_why": str}

    Args:
        name: the chosen term.
        e_win: (R,) its check L1 per recording.
        e_ref: (R,) the reference's.
        others: (name, (R,) check L1) of the other nameable candidates (:func:`deform.diagnose.scoring.nameable`).
        confidence: of the bootstrap intervals.
    """
    members, why = [name], []
    for other, e in others:
        d = (np.asarray(e) - np.asarray(e_win)) / np.asarray(e_ref)
        lo, hi = bootstrap_ci(d, confidence)
        if lo <= 0.0:
            members.append(other)
            why.append(
                f"{other}: check error {d.mean() * 100:+.1f} % of the reference relative to {name}, "
                f"{confidence * 100:.0f} % interval [{lo * 100:+.1f}, {hi * 100:+.1f}] % holds 0"
            )
    return {"equivalence_class": members, "equivalence_why": why}


NOISE_SEED = 101  # the refit's windows: the candidate budget's seed plus this


@dataclass
class NoiseRefit:
    """The chosen candidate and its reference to be fitted again on other windows of fit/ (the
    budget's seed plus :data:`NOISE_SEED`): how much of the improvement is the fit's own noise.
    Independent of the next round, so it is fitted with that round's fits of the same budget, as
    one batch, or alone (:func:`fit_noise`) when there is none."""

    name: str
    nominal: Nominal  # the start of the chosen candidate's fit
    members: list  # (terms, index of the new one): the reference's and the candidate's
    budget: FitBudget  # the chosen candidate's
    improvement: float  # the improvement measured first
    entry: dict  # the candidate's report entry, which receives "fit_noise"

    @classmethod
    def of(cls, spec, nominal, selected, name, s, context, budget, improvement, entry, read_roll=True):
        term = make_term(name, spec.n_vertices, s, context, read_roll=read_roll)
        members = [
            ([copy.deepcopy(t) for t in selected], None),
            ([copy.deepcopy(t) for t in selected] + [term], len(selected)),
        ]
        return cls(name, nominal, members, budget, improvement, entry)

    @property
    def seed(self) -> int:
        return self.budget.seed + NOISE_SEED

    def fits_with(self, budget: FitBudget) -> bool:
        """Whether its fits can be stepped with fits of ``budget`` (the same but for the seed)."""
        return dataclasses.replace(self.budget, seed=budget.seed, progress=budget.progress) == budget

    def record(self, c_ref: CheckErrors, c: CheckErrors) -> None:
        """Store ``{"improvement_refit", "noise"}`` from the refits' check errors."""
        again = float(((c_ref.window - c.window) / c_ref.window).mean())
        self.entry["fit_noise"] = {"improvement_refit": again, "noise": abs(again - self.improvement)}


def fit_noise(refit: NoiseRefit, spec, pool: FitPool) -> None:
    """:class:`NoiseRefit`'s two fits as one batch of their own."""
    other = dataclasses.replace(refit.budget, seed=refit.seed, progress=False)
    future = pool.submit(fit_together_job, spec, refit.nominal, refit.members, other, f"refit: {refit.name}")
    (_, c_ref), (_, c) = _gather([future], pool, "refit")[0]
    refit.record(c_ref, c)


def _models(budget: FitBudget, term) -> int:
    """Models a candidate's fit descends: one per start of its grid (at most ``budget.starts``)."""
    return min(budget.starts, 1 + len(term.grid())) if term.grid() and budget.starts > 1 else 1


def _label(key: tuple) -> str:
    """A fit's name in a group's progress label."""
    kind, name = key
    return {"candidate": name, "reference": "reference", "noise": f"{name} refit"}[kind]


def selected_uncertainty(sim: Simulator, selected: list[Term], recordings, budget_for) -> list[dict]:
    """The Laplace 1-sigma (:func:`deform.diagnose.fitting.laplace_uncertainty`) of each selected
    term's parameters in the final simulator ``sim``, on the windows the term was fitted on
    (``budget_for(term)``: a slow term's loss is flat on the short ones).

    Why the simulator's own copy of each term: a later round fits copies of the terms chosen before
    it, so only the last chosen term object is in ``sim``; perturbing an earlier one left the loss
    unchanged, and its parameters were reported as undetermined.
    """
    out = []
    for t in selected:
        held = next(x for x in sim.terms if x.name == t.name)
        out.append(laplace_uncertainty(sim, recordings, budget_for(t), held))
    return out


def model_step_for(term: Term, selected: list[Term], slow_step_s: float | None) -> float | None:
    """The longest model step [s] a candidate is fitted with: ``slow_step_s`` for a slow term
    (:attr:`Term.slow`) and for every term once a slow one is selected (its fitted size holds at
    the step it was fitted with), else None (:data:`simulator.MAX_STEP_S`).

    Args:
        term: the candidate.
        selected: terms selected in earlier rounds.
        slow_step_s: :attr:`DiagnoseBudget.slow_step_s`.
    """
    if slow_step_s is None or not (term.slow or any(t.slow for t in selected)):
        return None
    return slow_step_s


def refit_reference(
    spec, nominal, selected, inputs: Inputs, budget: FitBudget, current: CheckErrors, desc: str
) -> CheckErrors:
    """The current model (``nominal`` and the ``selected`` terms) refitted with a candidate's budget,
    so that a candidate is credited only for what its physics adds, not for the extra optimisation;
    ``current`` (the model's own check errors) when the refit came out worse, which must not make
    candidates look good.

    Args:
        spec: the rod.
        nominal: the nominal parameters (copied).
        selected: terms selected in earlier rounds (copied).
        inputs: fit and check recordings.
        budget: the candidate's fit budget.
        current: check errors of the model as it stands.
        desc: progress label.
    """
    _, c = fit_and_check(spec, nominal, [copy.deepcopy(t) for t in selected], inputs, budget, desc)
    return current if c.window.mean() > current.window.mean() else c


def _gather(futures: list, pool: FitPool, desc: str) -> list:
    """The results of ``futures`` in their order; with worker processes, one bar of finished fits."""
    if pool.parallel and futures:
        for _ in tqdm(as_completed(futures), total=len(futures), desc=desc, unit="fit", leave=False):
            pass
    return [f.result() for f in futures]


def fit_cost(tb: FitBudget) -> float:
    """A fit's relative cost, to send the longest first: model steps per frame (a shorter step
    takes more) and window growth (longer rollouts through the same number of rod-steps)."""
    cost = MAX_STEP_S / (tb.max_step_s or MAX_STEP_S)
    return cost * (1.5 if tb.final_horizon else 1.0)


def diagnose(
    inputs: Inputs, budget: DiagnoseBudget | None = None, start_model: str | None = None, workers: int = 1
) -> Diagnosis:
    """Run the whole tool: nominal fit, localisation, candidates fitted and scored in forward
    selection rounds, equivalence classes and fit noise of the chosen terms.

    Args:
        inputs: from :func:`deform.diagnose.spec.load_inputs`.
        budget: the work to spend (default: the full budget).
        start_model: a DEFORM checkpoint to start the nominal parameters from, or None.
        workers: processes that fit a round's independent candidates side by side
            (:mod:`deform.diagnose.pool`); the result does not depend on it.

    Returns:
        The :class:`Diagnosis` (``report`` is report.json's content).
    """
    with FitPool(inputs, workers) as pool:
        return _diagnose(inputs, budget or DiagnoseBudget(), start_model, pool)


def _diagnose(inputs: Inputs, budget: DiagnoseBudget, start_model: str | None, pool: FitPool) -> Diagnosis:
    t0 = time.perf_counter()
    spec = inputs.spec
    s = arclength_of(inputs.fit)
    cb = dataclasses.replace(budget.candidate, progress=budget.progress and not pool.parallel)
    nominal = _nominal_from_model(start_model) if start_model else Nominal()
    nominal.set_clamp(budget.clamp_m, fitted=budget.fit_clamp)
    start = copy.deepcopy(nominal)
    nb = dataclasses.replace(cb, iterations=budget.nominal_iterations)
    from_model = bool(start_model)
    # round 1 starts slow terms from a nominal fit at the slow step (fine_nominal): it needs only
    # the start, so it is fitted with the 10 ms one, the two stepped as one batch
    # (deform.diagnose.stack: each its own model step)
    wants_fine = (
        budget.fine_nominal
        and budget.slow_step_s is not None
        and budget.max_rounds > 0
        and any(LIBRARY[name].slow for name in budget.candidates)
    )
    steps = [MAX_STEP_S] + ([budget.slow_step_s] if wants_fine else [])
    nominal_future = pool.submit(nominal_fits_job, spec, start, nb, steps, "nominal fit", from_model)
    nominals = _gather([nominal_future], pool, "nominal fit")[0]
    sim, coarse, clamp_restart, c_nom = nominals[0]
    nominal = sim.nominal
    e_nom = c_nom.rollout
    loc_recs = (inputs.fit[: budget.localization_recordings // 2] + inputs.check)[
        : budget.localization_recordings
    ]
    res = short_rollout_residuals(sim, loc_recs)
    loc = localize(res, s)
    if sim.nominal.at_damping_bound():
        loc["findings"].insert(
            0,
            f"the nominal fit wants more velocity damping than a rope's material damping gives "
            f"(held at {sim.nominal.damping_max:g} /s, 2x the controls'): external dissipation "
            "(air drag, contact friction) or strong internal damping",
        )
    context = {
        "lowest_z": min(float(r.positions[:, 2:-2, 2].min()) for r in inputs.fit),
        "peak_s": loc["peak_s"],
        "contact_z": contact_height(loc),
    }
    selected: list = []
    selected_names: list[str] = []
    base_nominal, base_err, base_sim = nominal, c_nom, sim
    remaining = list(budget.candidates)
    candidates_out: list[dict] = []
    slow_cb = dataclasses.replace(cb, final_horizon=CHECK_HORIZON if budget.grow_slow_terms else None)
    fine: dict = {}  # the nominal fit at slow_step_s (fine_nominal), once round 1 uses it
    noise: NoiseRefit | None = None  # the last choice's refit, not yet fitted

    def from_fine_nominal(term: Term, rnd: int) -> bool:
        """Whether a candidate starts from the nominal model fitted at the slow step: in round 1,
        a slow term with :attr:`DiagnoseBudget.fine_nominal`."""
        return rnd == 0 and term.slow and budget.slow_step_s is not None and budget.fine_nominal

    def base_for(from_fine: bool) -> tuple[Nominal, CheckErrors]:
        """What a candidate starts from and its reference falls back to: the current model, or the
        nominal model fitted at the slow step, falling back to the better of its and the 10 ms
        fit's check errors."""
        if not from_fine:
            return base_nominal, base_err
        if not fine:
            fsim, _, _, checked = nominals[1]
            fine.update(sim=fsim, checked=checked)
            fine["current"] = checked if checked.window.mean() < c_nom.window.mean() else c_nom
        return fine["sim"].nominal, fine["current"]

    def budget_for(term: Term) -> FitBudget:
        """A term's fit budget: slow terms on windows growing to the scoring windows (see
        :attr:`DiagnoseBudget.grow_slow_terms`), the others on the candidate budget's; slow terms,
        and every term once one is selected, with the model's step at most
        :attr:`DiagnoseBudget.slow_step_s`."""
        tb = slow_cb if term.slow else cb
        return dataclasses.replace(tb, max_step_s=model_step_for(term, selected, budget.slow_step_s))

    for rnd in range(budget.max_rounds):
        if not remaining:
            break
        plans = []
        for name in remaining:
            term = make_term(name, spec.n_vertices, s, context, read_roll=budget.read_roll)
            tb = budget_for(term)
            from_fine = bool(from_fine_nominal(term, rnd))
            plans.append((name, term, tb, (tb.final_horizon, tb.max_step_s, from_fine)))

        # a reference per fit-window kind and step (fitted once per round), and every candidate:
        # all independent. The fits of one kind are stepped together in groups
        # (deform.diagnose.stack), chosen from the round's candidates alone: the numbers do not
        # depend on the workers
        kinds: list[tuple] = []
        items: dict[tuple, list] = {}  # kind -> [(key, Member, models)]
        for name, term, tb, kind in plans:
            if kind not in kinds:
                kinds.append(kind)
                refs = [copy.deepcopy(t) for t in selected]
                items.setdefault(kind, []).append((("reference", kind), Member(refs, None), 1))
            terms = [copy.deepcopy(t) for t in selected] + [term]
            items.setdefault(kind, []).append(
                (("candidate", name), Member(terms, len(selected)), _models(tb, term))
            )
        budgets = {kind: tb for _, _, tb, kind in reversed(plans)}  # a kind's budget: its first plan's
        if noise is not None:  # the last choice's refit, with this round's fits of its budget
            kind = next((k for k in kinds if noise.fits_with(budgets[k])), None)
            if kind is None:
                fit_noise(noise, spec, pool)
                noise = None
            else:
                for key, (terms, index) in zip(("reference", "candidate"), noise.members):
                    models = _models(budgets[kind], terms[index]) if index is not None else 1
                    member = Member(terms, index, noise.nominal, noise.seed)
                    items[kind].append((("noise", key), member, models))
        jobs, groups = [], []
        for kind, listed in items.items():
            tb = budgets[kind]
            for members in groups_of([models for *_, models in listed]):
                group = [listed[i] for i in members]
                label = ", ".join(_label(key) for key, *_ in group)
                desc = f"round {rnd + 1}: {label}"

                def make(kind=kind, group=group, tb=tb, desc=desc):
                    fits = [member for _, member, _ in group]
                    return fit_together_job, (spec, base_for(kind[2])[0], fits, tb, desc)

                cost = fit_cost(tb) * (1 + 0.1 * sum(models for *_, models in group))
                jobs.append(Job(("group", len(groups)), cost, make))
                groups.append([key for key, *_ in group])
        ran = pool.run(jobs, f"round {rnd + 1}")
        out = {key: r for g, keys in enumerate(groups) for key, r in zip(keys, ran[("group", g)])}
        if noise is not None:
            noise.record(out[("noise", "reference")][1], out[("noise", "candidate")][1])
            noise = None
        done = [out[("reference", k)] for k in kinds] + [out[("candidate", p[0])] for p in plans]
        references: dict[tuple, CheckErrors] = {}
        for kind, (_, c) in zip(kinds, done[: len(kinds)]):
            current = base_for(kind[2])[1]
            references[kind] = current if c.window.mean() > current.window.mean() else c
        results = []
        for (name, _, tb, kind), (csim, checked) in zip(plans, done[len(kinds) :]):
            term = csim.terms[len(selected)]  # the fitted one (a copy, when it came from a worker)
            start_nominal = base_for(kind[2])[0]
            c_ref = references[kind]
            e_ref = c_ref.window
            sc = score(e_ref, checked.window, term.n_params)
            params = term.params()
            named = nameable(name, params, sc.improvement, sc.ci_low, sc.threshold)
            results.append(FittedCandidate(name, term, csim, checked, sc, e_ref, tb, named, start_nominal))
            candidates_out.append(
                {
                    "name": name,
                    "params": params,
                    "check_l1_m": float(checked.rollout.mean()),
                    "check_window_l1_m": float(checked.window.mean()),
                    "improvement": sc.improvement,
                    "improvement_rollout": float(((c_ref.rollout - checked.rollout) / c_ref.rollout).mean()),
                    "significant": sc.significant,
                    "beyond_material_level": beyond_material_level(name, params),
                    "nameable": named,
                    "round": rnd + 1,
                    "on_top_of": list(selected_names),
                    "n_params": term.n_params,
                    "improvement_ci90": [sc.ci_low, sc.ci_high],
                    "improvement_by_check_recording": ((e_ref - checked.window) / e_ref).tolist(),
                    "threshold": sc.threshold,
                    "reference_check_l1_m": float(c_ref.rollout.mean()),
                    "reference_check_window_l1_m": float(e_ref.mean()),
                    "growing_windows": tb.final_horizon is not None,
                    "model_step_s": csim.model.dt,
                    "from_fine_nominal": kind[2],
                }
            )
        choice = choose([c for c in candidates_out if c["round"] == rnd + 1])
        if choice.held_by is not None:  # rule v9: the rope's own material physics does as well
            pick, held = choice.best, choice.held_by
            pick["held_by_material_level"] = {
                "term": held["name"],
                "term_penalised": penalised(held["improvement"], held["n_params"]),
                "pick_penalised": penalised(pick["improvement"], pick["n_params"]),
            }
        if choice.named is None:
            break
        sig = [r for r in results if r.nameable]
        best = next(r for r in sig if r.name == choice.named["name"])
        name = best.name
        cls = equivalence_class(
            name,
            best.checked.window,
            best.reference,
            [(r.name, r.checked.window) for r in sig if r.name != name],
        )
        entry = next(c for c in candidates_out if c["name"] == name and c["round"] == rnd + 1)
        entry.update(cls)
        noise = NoiseRefit.of(
            spec,
            best.base,
            selected,
            name,
            s,
            context,
            best.budget,
            best.score.improvement,
            entry,
            read_roll=budget.read_roll,
        )
        selected.append(best.term)
        selected_names.append(name)
        base_nominal, base_err, base_sim = best.sim.nominal, best.checked, best.sim
        order = sorted((r for r in results if r.name != name), key=lambda r: -r.score.improvement)
        remaining = [r.name for r in order if r.score.improvement > 0][: budget.later_round_candidates]
    if noise is not None:  # the last choice's refit: no later round to join
        fit_noise(noise, spec, pool)
    for t, std in zip(
        selected, selected_uncertainty(base_sim, selected, inputs.fit, budget_for), strict=True
    ):
        for c in candidates_out:
            if c["name"] == t.name and c["on_top_of"] == selected_names[: selected_names.index(t.name)]:
                c["params_std"] = std
    report = {
        "nominal": {
            "params": nominal.params(),
            "check_l1_m": float(e_nom.mean()),
            "check_window_l1_m": float(c_nom.window.mean()),
            "check_l1_by_recording_m": dict(zip([r.name for r in inputs.check], e_nom.tolist())),
            "coarse_identification": coarse,
            "clamp_fitted": budget.fit_clamp,
            "model_step_s": sim.model.dt,
            "fine": None
            if not fine
            else {
                "params": fine["sim"].nominal.params(),
                "model_step_s": fine["sim"].model.dt,
                "check_l1_m": float(fine["checked"].rollout.mean()),
                "check_window_l1_m": float(fine["checked"].window.mean()),
            },
            "clamp_restart": clamp_restart,
            "warnings": list(inputs.warnings),
        },
        "localization": loc,
        "candidates": candidates_out,
        "selected": selected_names,
        "final_check_l1_m": float(base_err.rollout.mean()),
    }
    report["nominal"]["final_params"] = {
        "nominal": base_nominal.params(),
        **{t.name: t.params() for t in selected},
    }
    report["nominal"]["final_check_window_l1_m"] = float(base_err.window.mean())
    report["nominal"]["seconds"] = time.perf_counter() - t0
    return Diagnosis(report=report, nominal_sim=sim, final_sim=base_sim, residuals=res)
