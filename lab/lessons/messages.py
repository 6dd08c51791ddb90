"""What a grading run tells the student: failures of their code, outcomes, hints, the variants of the data.

Every hint line reads ``Hint: <text> [<name>]`` (:func:`hints_text`; :func:`hint_names` reads the names
back); a check run on several variants of its data lists the variants that failed, each message once
(:func:`variants_text`).
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from lab.lessons import checks as checks_module
from lab.lessons import mutants as mutants_module
from lab.lessons.checks import Hint
from lab.lessons.format import CheckDataset, Limits
from lab.lessons.sandbox import SubmissionFailure


def failure_kind_text(failure: SubmissionFailure) -> str:
    return {"timeout": "it did not return in time", "cpu": "it used up its CPU time",
            "crashed": "the process running it died", "load": "the file could not be loaded"}.get(
        failure.kind, failure.kind)


def failure_text(failure: SubmissionFailure | None, what: str, limits: Limits) -> str:
    if failure is None:
        return ""
    if failure.kind == "raised":
        if failure.type_name == "NotImplementedError":
            text = (f"{what} is not implemented yet: it raised NotImplementedError. Replace the "
                    f"`raise NotImplementedError` in starter.py with your code.")
        else:
            text = f"{what} raised {failure.type_name}: {failure.message}"
            hint = exception_hint(failure)
            if hint:
                text += f"\nHint: {hint}"
        if failure.traceback and failure.type_name != "NotImplementedError":
            text += f"\n{failure.traceback}"
        return text
    if failure.kind == "blocked":
        tried = f" (it tried: {'; '.join(failure.violations)})" if failure.violations else ""
        return (f"{what} tried something submissions may not do{tried}: {failure.message}\n"
                f"Submissions may use numpy, scipy and cv2 and the files in their own directory only.")
    if failure.kind == "memory":
        detail = f": {failure.message}" if failure.message else ""
        return (f"{what} ran out of memory{detail}. A submission may allocate {limits.memory_mb:g} MB; keep "
                f"arrays the size of the inputs.\n{failure.traceback}")
    if failure.kind == "load" and failure.traceback:
        return f"{failure.message}\n{failure.traceback}"
    return failure.message


def exception_hint(failure: SubmissionFailure) -> str:
    message = failure.message
    if failure.type_name == "LinAlgError" and "SVD did not converge" in message:
        return "the matrix you decompose contains NaN or infinite entries (a division by zero earlier?)"
    if failure.type_name == "ValueError" and ("could not broadcast" in message or "shapes" in message):
        return "array shapes do not match: print the shapes of the arrays on the failing line"
    if failure.type_name == "IndexError":
        return "an index is out of range: check the shapes of the inputs (they are in the docstring)"
    if failure.type_name == "TypeError" and "argument" in message:
        return "the pipeline calls your function with the parameters of starter.py: keep them unchanged"
    return ""


def nan_hint(reason: str) -> str:
    if "NaN" in reason:
        return " (a division by zero, or the square root of a negative number?)"
    return ""


def outcome_text(outcome: checks_module.Outcome, what: str, hints: list[Hint]) -> str:
    return f"{'Passed' if outcome.passed else 'Failed'}: {what}: {outcome.message()}" + hints_text(hints)


def hints_text(hints: list[Hint]) -> str:
    """``Hint: <text> [<name>]`` lines, each text once."""
    seen: dict[str, str] = {}
    for hint in hints:
        seen.setdefault(hint.text, hint.name)
    return "".join(f"\nHint: {text} [{name}]" for text, name in seen.items())


HINT_LINE = re.compile(r"^Hint: .* \[([^\]]+)\]$", re.M)


#: A detector that is not sure asks: when this share of the entries (and not all) matches an alternative
#: that the reference's result mostly does not match.
PARTIAL_MATCH = 0.9


def partial_match(candidates: list[tuple[mutants_module.Mutant, Any]], got: np.ndarray,
                   expected: np.ndarray) -> list[Hint]:
    """A question for the alternative most of whose entries (at least :data:`PARTIAL_MATCH`, not all) the
    student's result equals, where the reference's equals few (at most half): a mistake plus something else,
    or a mistake the border of an array hides (a shift that fills the edge another way)."""
    if got.size < 10:
        return []
    scale = float(np.abs(expected).max()) or 1.0
    best: tuple[float, mutants_module.Mutant] | None = None
    for mutant, alternative in candidates:
        try:
            alt = checks_module.as_compared(alternative)
        except (TypeError, ValueError):
            continue
        if alt.shape != got.shape:
            continue
        close = np.abs(got - alt) <= 1e-6 * np.abs(alt) + 1e-9 * scale
        reference_close = np.abs(expected - alt) <= 1e-6 * np.abs(alt) + 1e-9 * scale
        share = float(close.mean())
        better = best is None or share > best[0]
        if PARTIAL_MATCH <= share < 1.0 and reference_close.mean() <= 0.5 and better:
            best = (share, mutant)
    if best is None:
        return []
    share, mutant = best
    return [Hint(mutant.name, f"{100 * share:.0f} % of your entries equal the result {mutant.question}: "
                              "is that the mistake?")]


def structure_hint(got: Any, expected: Any) -> str:
    hint = checks_module.structure_hint(got, expected)
    return hints_text([hint]) if hint else ""


def hint_names(body: str) -> list[str]:
    """The names of the hints a message gives (its ``Hint: ... [name]`` lines)."""
    return HINT_LINE.findall(body)


def variants_text(data: CheckDataset, bodies: dict[int, tuple[str, bool]]) -> str:
    """What a check found on the variants of its data: the one body when there is one variant; else whether
    all passed, or each failing variant (described) with its message, the same message written once."""
    if len(bodies) == 1:
        return next(iter(bodies.values()))[0]
    count = len(bodies)
    failing = [k for k in sorted(bodies) if not bodies[k][1]]
    if not failing:
        return f"Passed on all {count} variants of the data.\n{bodies[0][0]}"
    lines = [f"Failed on {len(failing)} of the {count} variants of the data "
             f"(variant{'s' if len(failing) > 1 else ''} {', '.join(str(k + 1) for k in failing)})."]
    by_body: dict[str, list[int]] = {}
    for k in failing:
        by_body.setdefault(bodies[k][0], []).append(k)
    for body, variants in by_body.items():
        which = ", ".join(str(k + 1) for k in variants)
        if len(variants) == 1:
            lines.append(f"Variant {which}: {data.describe(variants[0])}\n{body}")
            continue
        described = "\n".join(f"  variant {k + 1}: {data.describe(k, numbered=False)}" for k in variants)
        lines.append(f"Variants {which}:\n{described}\n{body}")
    return "\n".join(lines)


def format_params(params: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v!r}" for k, v in params.items())


def truncate(text: str, limit: int) -> str:
    if len(text) <= limit:
        return text
    return text[:limit] + f"\n... ({len(text) - limit} more characters not shown)"
