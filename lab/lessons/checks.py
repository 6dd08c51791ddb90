"""Comparisons and mistake detectors the grader uses; each is a small typed function with a clear message.

A **comparison** ``compare(got, expected, **options) -> Outcome`` decides one check: ``got`` is
what the student's code produced (or a metric of the pipeline run on it), ``expected`` the
reference's on the same data. ``tasks.toml`` names it (``compare = "equal_up_to_scale"``) and
gives its options (``rtol = 1e-6``), which :func:`check_options` validates at load time.

A **detector** ``detect(got, expected, **options) -> str | None`` recognises a common mistake
and returns a hint for the student ("F has rank 3: enforce rank 2"), or None. A lesson defines
its hints once (``[hints.rank_3] when = "rank_above"``, ``rank = 2``, ``say = "..."``) and a check
names the ones worth trying (``hints = ["rank_3", "transposed"]``: a detector that needs no
options is named directly); they run only when it fails.

:func:`structure_problem` checks what came back before any comparison: its type, shape, dtype and
that it is finite, with the hint a wrong shape suggests.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from dataclasses import dataclass
from typing import Any
from collections.abc import Callable

import numpy as np


@dataclass(frozen=True)
class Outcome:
    """The result of one comparison: passed or not, a one-line measurement, and the values shown."""

    passed: bool
    summary: str
    expected: str = ""
    got: str = ""

    def message(self) -> str:
        lines = [self.summary]
        if not self.passed and self.expected:
            lines += ["Expected:", self.expected, "Got:", self.got]
        return "\n".join(lines)


@dataclass(frozen=True)
class Hint:
    """What a failed check tells the student about the cause: ``name`` (a ``[hints]`` key of the lesson, a
    detector, a mutant or a function of ``mistakes.py``; shown as ``[name]``) and the text."""

    name: str
    text: str


def show(value: Any) -> str:
    """A short readable form of an array or number for messages."""
    array = np.asarray(value)
    if array.ndim == 0:
        return _number(array.item())
    with np.printoptions(precision=6, suppress=True, threshold=40, edgeitems=3, linewidth=90):
        return str(array)


def _number(value: Any) -> str:
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    try:
        return f"{float(value):.6g}"
    except (TypeError, ValueError):
        return repr(value)


def _items(array: np.ndarray, items: bool) -> np.ndarray:
    """``(M, ...)`` -> ``(M, K)``: one row per independent object (e.g. one homography per view)."""
    array = np.asarray(array, dtype=np.float64)
    if items and array.ndim >= 3:
        return array.reshape(len(array), -1)
    return array.reshape(1, -1)


def _item_label(array: np.ndarray, index: int, items: bool) -> str:
    return f" (item {index})" if items and np.ndim(array) >= 3 else ""


def _pick(array: Any, index: int, items: bool) -> np.ndarray:
    array = np.asarray(array)
    return array[index] if items and array.ndim >= 3 else array


# --- comparisons --------------------------------------------------------------------------------
def allclose(got: np.ndarray, expected: np.ndarray, *, rtol: float = 1e-6, atol: float = 1e-9) -> Outcome:
    """Every entry within ``atol + rtol * |expected|`` (``numpy.allclose``)."""
    got = np.asarray(got, dtype=np.float64)
    expected = np.asarray(expected, dtype=np.float64)
    difference = np.abs(got - expected)
    allowed = atol + rtol * np.abs(expected)
    excess = difference - allowed
    worst = np.unravel_index(int(np.argmax(excess)), excess.shape) if excess.size else ()
    passed = bool(np.all(excess <= 0))
    if expected.ndim == 0:
        summary = (f"got {_number(got.item())}, expected {_number(expected.item())} "
                   f"(difference {difference.item():.3g}, allowed {allowed.item():.3g})")
        return Outcome(passed, summary)
    at = f" at index {list(map(int, worst))}" if worst else ""
    summary = (f"largest difference {difference[worst]:.3g}{at}; allowed there {allowed[worst]:.3g} "
               f"(atol {atol:g} + rtol {rtol:g} x |expected|)")
    item = int(worst[0]) if expected.ndim >= 3 and worst else 0
    label = f" (item {item})" if expected.ndim >= 3 else ""
    return Outcome(passed, summary, show(_pick(expected, item, True)) + label,
                   show(_pick(got, item, True)) + label)


def equal_up_to_scale(got: np.ndarray, expected: np.ndarray, *, rtol: float = 1e-6,
                      items: bool = True) -> Outcome:
    """Equal after the best scale factor (homographies, F, E): ``min_s |s got - expected| / |expected|``.

    With ``items`` (default) each entry of the first axis of a stack (``(M, 3, 3)``) has its own scale.
    """
    g, e = _items(got, items), _items(expected, items)
    errors = np.empty(len(e))
    for i, (gi, ei) in enumerate(zip(g, e, strict=False)):
        norm = float(gi @ gi)
        if norm == 0.0:
            errors[i] = math.inf
            continue
        scale = float(gi @ ei) / norm
        errors[i] = float(np.linalg.norm(scale * gi - ei) / max(float(np.linalg.norm(ei)), 1e-300))
    worst = int(np.argmax(errors))
    passed = bool(np.all(errors <= rtol))
    label = _item_label(expected, worst, items)
    zero = " (it is all zeros)" if math.isinf(errors[worst]) else ""
    summary = (f"relative difference after the best scale factor: {errors[worst]:.3g}{label}{zero}; "
               f"allowed {rtol:g}")
    return Outcome(passed, summary, show(_normalized(_pick(expected, worst, items))) + label,
                   show(_normalized(_pick(got, worst, items))) + label)


def _normalized(array: np.ndarray) -> np.ndarray:
    """Scaled for display so that the largest entry is 1 (shows 'equal up to scale' side by side)."""
    array = np.asarray(array, dtype=np.float64)
    peak = array.flat[int(np.argmax(np.abs(array)))] if array.size else 1.0
    return array / peak if peak else array


def equal_up_to_sign(got: np.ndarray, expected: np.ndarray, *, rtol: float = 1e-6, atol: float = 1e-9,
                     items: bool = True) -> Outcome:
    """``allclose`` to ``expected`` or to ``-expected`` (each item choosing its sign): null vectors,
    epipoles."""
    g, e = _items(got, items), _items(expected, items)
    flipped = np.array([np.abs(-gi - ei).max() < np.abs(gi - ei).max() for gi, ei in zip(g, e, strict=False)])
    signs = np.where(flipped, -1.0, 1.0)
    aligned = (g * signs[:, None]).reshape(np.shape(expected)) if np.shape(got) == np.shape(expected) else got
    outcome = allclose(aligned, expected, rtol=rtol, atol=atol)
    return dataclasses.replace(outcome, summary=outcome.summary + " (after choosing the sign)")


def _item_rows(value: np.ndarray) -> np.ndarray:
    """``(M, ...)`` -> ``(M, K)`` rows, one per item."""
    array = np.asarray(value, dtype=np.float64)
    return array.reshape(len(array), -1) if array.ndim >= 2 else array.reshape(-1, 1)


def same_set(got: np.ndarray, expected: np.ndarray, *, rtol: float = 1e-6, atol: float = 1e-9,
             up_to: str = "exact") -> Outcome:
    """The items along the first axis equal the expected ones in some order (each matched once):
    pose candidates, a set of solutions. ``up_to``: ``"exact"`` (``allclose`` per item), ``"sign"``
    (an item may be negated) or ``"scale"`` (an item may have any scale). The matching is the
    assignment of least total error (``scipy.optimize.linear_sum_assignment``).
    """
    from scipy.optimize import linear_sum_assignment

    if up_to not in ("exact", "sign", "scale"):
        raise ValueError(f'up_to must be "exact", "sign" or "scale", got {up_to!r}')
    g, e = _item_rows(got), _item_rows(expected)
    if g.shape != e.shape:
        return Outcome(False, f"{len(g)} items of size {g.shape[1]}; expected {len(e)} of size {e.shape[1]}")
    scale = np.maximum(atol + rtol * np.abs(e), 1e-300)  # per expected entry

    def excess(gi: np.ndarray) -> np.ndarray:
        """How far item ``gi`` is from every expected item, in units of the allowed difference: ``(M,)``."""
        if up_to == "scale":
            norm = float(gi @ gi)
            candidates = [np.outer(e @ gi / norm, gi)] if norm else [np.broadcast_to(gi, e.shape)]
        else:
            candidates = [np.broadcast_to(gi, e.shape)]
            if up_to == "sign":
                candidates.append(np.broadcast_to(-gi, e.shape))
        return np.min([np.max(np.abs(c - e) / scale, axis=1) for c in candidates], axis=0)

    cost = np.stack([excess(gi) for gi in g])  # (M, M): got item i against expected item j
    rows, cols = linear_sum_assignment(np.minimum(cost, 1e300))
    worst = int(np.argmax(cost[rows, cols]))
    ratio = float(cost[rows[worst], cols[worst]])
    passed = ratio <= 1.0
    up = {"exact": "", "sign": " up to sign", "scale": " up to scale"}[up_to]
    summary = (f"each of your items matched to an expected one{up}, in any order: the worst match is "
               f"{ratio:.3g} x the allowed difference (atol {atol:g} + rtol {rtol:g} x |expected|)")
    shown_expected = show(np.asarray(expected)[cols[worst]]) + f" (expected item {cols[worst]})"
    shown_got = show(np.asarray(got)[rows[worst]]) + f" (your item {rows[worst]})"
    return Outcome(passed, summary, shown_expected, shown_got)


def rotation_angle(got: np.ndarray, expected: np.ndarray, *, max_deg: float = 0.1) -> Outcome:
    """The angle of ``got^T expected`` (``(..., 3, 3)`` rotations) at most ``max_deg`` degrees."""
    g = np.asarray(got, dtype=np.float64).reshape(-1, 3, 3)
    e = np.asarray(expected, dtype=np.float64).reshape(-1, 3, 3)
    cosine = (np.einsum("nji,nji->n", g, e) - 1.0) / 2.0
    angles = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    worst = int(np.argmax(angles))
    label = f" (item {worst})" if len(angles) > 1 else ""
    return Outcome(bool(np.all(angles <= max_deg)),
                   f"largest rotation angle between yours and the expected "
                   f"{angles[worst]:.3g} deg{label}; allowed {max_deg:g} deg",
                   show(e[worst]), show(g[worst]))


def relative_error(got: np.ndarray, expected: np.ndarray, *, max_relative: float = 1e-3) -> Outcome:
    """``|got - expected| / |expected|`` (Frobenius norms) at most ``max_relative``."""
    g = np.asarray(got, dtype=np.float64)
    e = np.asarray(expected, dtype=np.float64)
    error = float(np.linalg.norm(g - e) / max(float(np.linalg.norm(e)), 1e-300))
    return Outcome(error <= max_relative, f"relative error {error:.3g}; allowed {max_relative:g}", show(e),
                   show(g))


def psnr(got: np.ndarray, expected: np.ndarray, *, min_db: float, data_range: float = 1.0) -> Outcome:
    """Peak signal-to-noise ratio of ``got`` against ``expected`` (images in [0, data_range]) at least
    ``min_db``."""
    g = np.asarray(got, dtype=np.float64)
    e = np.asarray(expected, dtype=np.float64)
    mse = float(np.mean((g - e) ** 2))
    value = math.inf if mse == 0 else 10.0 * math.log10(data_range ** 2 / mse)
    return Outcome(value >= min_db, f"PSNR {value:.2f} dB; needed at least {min_db:g} dB")


def bad_pixel_rate(got: np.ndarray, expected: np.ndarray, *, threshold: float = 2.0,
                   max_rate: float = 0.1) -> Outcome:
    """Share of pixels (where ``expected`` is finite) off by more than ``threshold`` at most ``max_rate``."""
    g = np.asarray(got, dtype=np.float64)
    e = np.asarray(expected, dtype=np.float64)
    valid = np.isfinite(e)
    bad = ~(np.abs(g - e) <= threshold) & valid
    rate = float(bad.sum() / max(int(valid.sum()), 1))
    return Outcome(rate <= max_rate, f"{100 * rate:.2f} % of pixels off by more than {threshold:g}; "
                                     f"allowed {100 * max_rate:g} %")


def below(got: Any, expected: Any, *, bound: float) -> Outcome:
    """Every entry of ``got`` at most ``bound`` (reprojection error, bad-pixel rate); ``expected`` is
    shown."""
    g = np.asarray(got, dtype=np.float64)
    value = float(np.max(g)) if g.size else -math.inf
    return Outcome(bool(value <= bound), f"got {_number(value)}, needed at most {bound:g} "
                                         f"(the reference gets {show(expected)})")


def above(got: Any, expected: Any, *, bound: float) -> Outcome:
    """Every entry of ``got`` at least ``bound`` (PSNR, inlier ratio); ``expected`` is shown."""
    g = np.asarray(got, dtype=np.float64)
    value = float(np.min(g)) if g.size else math.inf
    return Outcome(bool(value >= bound), f"got {_number(value)}, needed at least {bound:g} "
                                         f"(the reference gets {show(expected)})")


def at_most_reference(got: Any, expected: Any, *, factor: float = 1.0, margin: float = 0.0) -> Outcome:
    """``got <= factor * expected + margin``: an error no worse than the reference's, within a tolerance."""
    g = float(np.max(np.asarray(got, dtype=np.float64)))
    e = float(np.max(np.asarray(expected, dtype=np.float64)))
    bound = factor * e + margin
    return Outcome(g <= bound, f"got {_number(g)}; the reference gets {_number(e)}, so at most "
                               f"{_number(bound)} is accepted ({factor:g} x reference + {margin:g})")


#: Comparisons by the name ``tasks.toml`` uses.
COMPARISONS: dict[str, Callable[..., Outcome]] = {f.__name__: f for f in (
    allclose, equal_up_to_scale, equal_up_to_sign, same_set, rotation_angle, relative_error, psnr,
    bad_pixel_rate, below, above, at_most_reference)}


def check_options(compare: str, options: dict[str, Any]) -> tuple[str, str] | None:
    """(key, reason) of the first option ``compare`` does not accept or is missing, else None."""
    signature = inspect.signature(COMPARISONS[compare])
    params = {p.name: p for p in signature.parameters.values() if p.kind == p.KEYWORD_ONLY}
    for key, value in options.items():
        if key not in params:
            return key, f"comparison {compare!r} has no option {key!r}; options are {sorted(params)}"
        default = params[key].default
        numeric = default is inspect.Parameter.empty or isinstance(default, (int, float))
        kind = bool if isinstance(default, bool) else (float if numeric else type(default))
        if kind is str and not isinstance(value, str):
            return key, f"must be a string, got {value!r}"
        if kind is bool and not isinstance(value, bool):
            return key, f"must be true or false, got {value!r}"
        if kind is float and (isinstance(value, bool) or not isinstance(value, (int, float))):
            return key, f"must be a number, got {value!r}"
    for name, param in params.items():
        if param.default is inspect.Parameter.empty and name not in options:
            return name, f"comparison {compare!r} needs option {name!r}"
    return None


# --- what came back -----------------------------------------------------------------------------
def structure_problem(got: Any, expected: Any, *, what: str) -> str | None:
    """Why ``got`` cannot be compared with ``expected`` (type, shape, dtype, NaN), or None."""
    if isinstance(expected, np.ndarray):
        if not isinstance(got, np.ndarray):
            return (f"{what} must be a numpy array (np.ndarray), got {type(got).__name__}"
                    + (": wrap it with np.asarray(...)" if isinstance(got, (list, tuple)) else ""))
        if got.dtype.kind not in "biuf" or (got.dtype.kind == "b" and expected.dtype.kind != "b"):
            return f"{what} must hold real numbers, got an array of dtype {got.dtype}"
        if got.shape != expected.shape:
            message = f"{what} has shape {got.shape}; expected shape {expected.shape}"
            if got.shape == expected.shape[1:]:
                message += f": one item where {expected.shape[0]} were expected (one per view?)"
            elif got.ndim == expected.ndim and got.shape[-2:] == expected.shape[-2:][::-1] and got.ndim >= 2:
                message += ": rows and columns swapped?"
            elif got.size == expected.size:
                message += f": reshape it to {expected.shape}"
            return message
        if got.dtype.kind == "f" and not np.all(np.isfinite(got)):
            bad = int(np.size(got) - np.count_nonzero(np.isfinite(got)))
            return f"{what} contains {bad} NaN or infinite entries (a division by zero, or an empty input?)"
        return None
    if isinstance(expected, (float, int, np.floating, np.integer)) and not isinstance(expected, bool):
        if isinstance(got, bool) or not isinstance(got, (float, int, np.floating, np.integer)):
            return f"{what} must be a number, got {type(got).__name__}"
        if not math.isfinite(float(got)):
            return f"{what} is {got}"
        return None
    if dataclasses.is_dataclass(expected) and not isinstance(expected, type):
        if type(got) is not type(expected):
            return f"{what} must be a {type(expected).__name__}, got {type(got).__name__}"
        for f in dataclasses.fields(expected):
            sub_expected, sub_got = getattr(expected, f.name), getattr(got, f.name)
            if sub_expected is None:
                continue
            if sub_got is None:
                return f"{what}.{f.name} is None; expected a value"
            problem = structure_problem(sub_got, sub_expected, what=f"{what}.{f.name}")
            if problem:
                return problem
        return None
    if type(got) is not type(expected):
        return f"{what} must be a {type(expected).__name__}, got {type(got).__name__}"
    return None


def select(value: Any, path: list[str], *, what: str) -> Any:
    """The field ``path`` of a typed value (``["xyz"]`` of a PointCloud); KeyError names what is missing."""
    for part in path:
        if not hasattr(value, part):
            raise KeyError(f"{what} has no field {part!r}")
        value = getattr(value, part)
    return value


def as_compared(value: Any) -> np.ndarray:
    """What comparisons see: a float64 array (a typed value compares by its primary array)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = [getattr(value, f.name) for f in dataclasses.fields(value)]
        if fields and isinstance(fields[0], tuple) and fields[0] \
                and all(dataclasses.is_dataclass(v) for v in fields[0]):
            return np.stack([as_compared(v) for v in fields[0]])  # an ImageSet: its images stacked
        arrays = [v for v in fields if isinstance(v, np.ndarray)]
        if not arrays:
            raise TypeError(f"{type(value).__name__} holds no array to compare")
        return np.asarray(arrays[0], dtype=np.float64)
    return np.asarray(value, dtype=np.float64)


# --- detectors of common mistakes ---------------------------------------------------------------
def _square_stack(array: np.ndarray) -> bool:
    return array.ndim >= 2 and array.shape[-1] == array.shape[-2]


def transposed(got: np.ndarray, expected: np.ndarray, *, rtol: float = 1e-3) -> str | None:
    """The matrix (each of a stack) is the expected one transposed, up to scale."""
    if got.shape != expected.shape or not _square_stack(got):
        return None
    if equal_up_to_scale(np.swapaxes(got, -1, -2), expected, rtol=rtol).passed \
            and not equal_up_to_scale(got, expected, rtol=rtol).passed:
        return ("your matrix is the expected one transposed (rows and columns swapped): check how you "
                "reshape the solution vector (row by row: h = (h11, h12, h13, h21, ...)) or how you index it")
    return None


def inverse(got: np.ndarray, expected: np.ndarray, *, rtol: float = 1e-3) -> str | None:
    """The matrix is the inverse of the expected one, up to scale: it maps the other way."""
    if got.shape != expected.shape or not _square_stack(got):
        return None
    try:
        inverted = np.linalg.inv(got)
    except np.linalg.LinAlgError:
        return None
    if equal_up_to_scale(inverted, expected, rtol=rtol).passed:
        return ("your matrix is the inverse of the expected one: it maps in the opposite direction "
                "(swap source and target)")
    return None


def negated(got: np.ndarray, expected: np.ndarray, *, rtol: float = 1e-3) -> str | None:
    """The result is the expected one with its sign flipped."""
    if got.shape == expected.shape and allclose(-got, expected, rtol=rtol, atol=1e-9).passed:
        return "your result is the expected one with the opposite sign"
    return None


def scaled(got: np.ndarray, expected: np.ndarray, *, rtol: float = 1e-3) -> str | None:
    """Right up to a scale factor, where the exact scale matters (a factor of -1 is :func:`negated`)."""
    if got.shape == expected.shape and equal_up_to_scale(got, expected, rtol=rtol).passed \
            and not allclose(got, expected, rtol=rtol, atol=1e-9).passed \
            and not allclose(-got, expected, rtol=rtol, atol=1e-9).passed:  # a sign flip is negated's
        return "your result is right up to a scale factor: normalise it as the task says"
    return None


def rank_above(got: np.ndarray, expected: np.ndarray, *, rank: int, rtol: float = 1e-7) -> str | None:
    """Some matrix of the stack has rank above ``rank`` (e.g. F with rank 3: enforce rank 2)."""
    if not _square_stack(got) and got.ndim < 2:
        return None
    values = np.linalg.svd(got.reshape(-1, *got.shape[-2:]), compute_uv=False)
    ranks = (values > rtol * values[:, :1]).sum(axis=1)
    if np.any(ranks > rank):
        return (f"your matrix has rank {int(ranks.max())}: enforce rank {rank} "
                f"(set its smallest singular value{'s' if values.shape[1] - rank > 1 else ''} to zero)")
    return None


def entry_zero(got: np.ndarray, expected: np.ndarray, *, index: list[int]) -> str | None:
    """``got[..., i, j]`` is exactly zero everywhere although the expected entry is not."""
    key: tuple[Any, ...] = (Ellipsis, *index)
    try:
        g, e = got[key], expected[key]
    except IndexError:
        return None
    scale = float(np.abs(expected).max()) or 1.0
    if np.all(g == 0) and np.any(np.abs(e) > 1e-12 * scale):
        return f"entry {list(index)} of your result is exactly 0, but the expected one is {show(e)}"
    return None


def entry_not(got: np.ndarray, expected: np.ndarray, *, index: list[int], value: float = 1.0,
              rtol: float = 1e-6) -> str | None:
    """``got[..., i, j]`` differs from ``value`` (e.g. H[2, 2] = 1 is the normalisation asked for)."""
    key: tuple[Any, ...] = (Ellipsis, *index)
    try:
        g = np.asarray(got[key], dtype=np.float64)
    except IndexError:
        return None
    if not np.allclose(g, value, rtol=rtol, atol=rtol):
        return f"entry {list(index)} of your result is {show(g)}, it must be {value:g}: divide by it"
    return None


def permuted(got: np.ndarray, expected: np.ndarray, *, rtol: float = 1e-3) -> str | None:
    """Every item of the stack matches a different expected item (exactly, not up to sign or scale), but in
    another order."""
    if got.shape != expected.shape or got.ndim < 2 or not 2 <= len(got) <= 1000:
        return None
    if allclose(got, expected, rtol=rtol, atol=1e-9).passed:
        return None
    if not same_set(got, expected, rtol=rtol, atol=1e-9 * max(float(np.abs(expected).max()), 1.0)).passed:
        return None
    return "each of your items matches an expected one, but in a different order: keep the order of the views"


def _rotation_blocks(array: np.ndarray) -> np.ndarray | None:
    """The ``3 x 3`` blocks of ``(..., 3, 3)`` rotations or ``(..., 3, 4)`` ``[R | t]``, else None."""
    if array.ndim < 2 or array.shape[-2] != 3 or array.shape[-1] not in (3, 4):
        return None
    return array[..., :3, :3].reshape(-1, 3, 3)


def reflection(got: np.ndarray, expected: np.ndarray) -> str | None:
    """A matrix that should be a rotation (det +1) is a reflection (det -1): an SVD factor not turned into a
    rotation, or a negated R."""
    g, e = _rotation_blocks(got), _rotation_blocks(expected)
    if g is None or e is None or g.shape != e.shape:
        return None
    expected_det, got_det = np.linalg.det(e), np.linalg.det(g)
    if not np.allclose(expected_det, 1.0, atol=1e-6):
        return None
    bad = np.flatnonzero(np.abs(got_det + 1.0) < 1e-3)
    if not len(bad):
        return None
    which = f" (item {int(bad[0])} of {len(g)})" if len(g) > 1 else ""
    return (f"your R has det {got_det[bad[0]]:.3g}{which}: a reflection, not a rotation. A rotation has "
            "det +1: negate an SVD factor (U or V^T) whose determinant is -1 before building R, rather than "
            "R itself")


def dtype_difference(got: Any, expected: Any) -> str | None:
    """The result has another dtype than the reference's and that explains the difference: float32 where
    float64 is expected (the difference is float32's rounding), or integers where floats are (rounded or
    truncated). On the raw values, before the grader turns them into float64."""
    got_array, expected_array = np.asarray(got), np.asarray(expected)
    if got_array.shape != expected_array.shape or expected_array.dtype.kind != "f" or got_array.size == 0:
        return None
    difference = np.abs(got_array.astype(np.float64) - expected_array)
    if not np.any(difference) or not np.all(np.isfinite(difference)):
        return None
    largest = float(difference.max())
    if got_array.dtype == np.float32 and expected_array.dtype == np.float64:
        allowed = 4 * np.finfo(np.float32).eps * (np.abs(expected_array) + np.abs(expected_array).max())
        if np.all(difference <= allowed):
            return (f"your result is float32 (dtype {got_array.dtype}), the expected is float64: the "
                    f"difference, {largest:.2g} at most, is float32's rounding. Compute in float64 (do not "
                    f"cast to np.float32)")
    if got_array.dtype.kind in "iu" and largest <= 1.0:
        return (f"your result holds integers (dtype {got_array.dtype}) where the expected holds floats "
                f"(float64): the values were rounded or truncated, by at most {largest:.2g}. Keep them as "
                f"floats (no astype(int), no // division)")
    return None


def structure_hint(got: Any, expected: Any) -> Hint | None:
    """A named hint for a value of the wrong form (its shape, NaN), beside :func:`structure_problem`'s."""
    if not isinstance(got, np.ndarray) or not isinstance(expected, np.ndarray):
        return None
    if got.shape != expected.shape:
        if got.shape == (*expected.shape, 1) or got.shape == (1, *expected.shape):
            return Hint("shape", f"your array has an extra axis of length 1: return shape {expected.shape} "
                                 "(np.ravel or np.squeeze it, or index with [:, 0])")
        if expected.shape == (*got.shape, 1):
            return Hint("shape", f"return shape {expected.shape}: one column, as a 2D array "
                                 "(reshape(-1, 1))")
        if got.ndim == expected.ndim >= 2 and got.shape[-2:] == expected.shape[-2:][::-1]:
            return Hint("shape", "rows and columns swapped: transpose your result or build it the other way")
        return None
    if got.dtype.kind == "f" and not np.all(np.isfinite(got)):
        return Hint("nan", "NaN or inf entries come from a division by zero, the log or square root of a "
                           "negative number, or an empty selection: print where np.isfinite(result) is False")
    return None


def same_as_reference_with(got: np.ndarray, expected: np.ndarray, *, alternative: Any = None,
                           outcome: Outcome | None = None,
                           params: dict[str, Any] | None = None) -> str | None:
    """The result equals the reference's run with other controls (the grader supplies ``outcome``)."""
    if outcome is not None and outcome.passed:
        return f"your result is what the reference computes with {params}"
    return None


def same_as_mistake(got: np.ndarray, expected: np.ndarray, *, outcome: Outcome | None = None,
                    mistake: str = "") -> str | None:
    """The result equals what a known wrong implementation of the lesson's ``mistakes.py`` computes on the
    same inputs (the grader runs it and supplies ``outcome``)."""
    if outcome is not None and outcome.passed:
        return f"your result is what the known mistake {mistake!r} computes"
    return None


#: Detectors by the name a hint's ``when`` uses.
DETECTORS: dict[str, Callable[..., str | None]] = {f.__name__: f for f in (
    transposed, inverse, negated, scaled, rank_above, entry_zero, entry_not, permuted, reflection,
    same_as_reference_with, same_as_mistake)}


#: Detectors the grader runs an alternative for (the reference with other controls, a function of
#: ``mistakes.py``) and compares: the keys their hints take in tasks.toml instead of options.
ALTERNATIVES: dict[str, frozenset[str]] = {
    "same_as_reference_with": frozenset({"params", "compare", "compare_options"}),
    "same_as_mistake": frozenset({"mistake", "compare", "compare_options"}),
}


def detector_keys(when: str) -> tuple[frozenset[str], frozenset[str]]:
    """(the keys a hint of detector ``when`` may give in tasks.toml, the ones it must give)."""
    if when in ALTERNATIVES:
        return ALTERNATIVES[when], frozenset({"mistake"} if when == "same_as_mistake" else ())
    parameters = list(inspect.signature(DETECTORS[when]).parameters.values())
    keys = [p for p in parameters if p.kind == p.KEYWORD_ONLY]
    return frozenset(p.name for p in keys), frozenset(p.name for p in keys if p.default is p.empty)


def plain_detectors() -> frozenset[str]:
    """Detectors that need no options: a check may name them directly (``hints = ["transposed"]``)."""
    return frozenset(name for name in DETECTORS if name not in ALTERNATIVES and not detector_keys(name)[1])


def detect(when: str, got: Any, expected: Any, options: dict[str, Any]) -> str | None:
    """Run detector ``when``; a detector that cannot apply (shapes, types) finds nothing."""
    try:
        return DETECTORS[when](np.asarray(got, dtype=np.float64), np.asarray(expected, dtype=np.float64),
                               **options)
    except (TypeError, ValueError, np.linalg.LinAlgError):
        return None
