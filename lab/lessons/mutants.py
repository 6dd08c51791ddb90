"""Mutants of a task's reference step: the mistakes a lesson's checks must catch, and that name a student's.

A :class:`Mutant` turns the reference function of a task's step into a wrong one with the same
parameters (mutation testing, DeMillo, Lipton & Sayward 1978; the operators are the array
mistakes students make). Three kinds are generated for any step (:func:`generic_mutants`):

``output``
    The reference's result transformed: ``transposed``, ``inverse``, ``scaled``, ``negated``,
    ``shifted`` by one along the first or the last axis, ``float32``, ``reversed`` order of a
    stack's items. A typed result (a ``@step_result`` dataclass) has its first array transformed.
``inputs``
    The reference called on other inputs: two same-shaped arguments ``swapped``, a boolean mask
    argument ``mask_dropped`` (every entry True).
``patch``
    The reference run with a NumPy function replaced for the call: ``argmax_for_argmin`` (and the
    other way), ``ties_other_way`` (the last of equal minima or maxima instead of the first).
    These reach only code that calls ``np.argmin`` / ``np.argmax`` (not a compiled kernel).

and the lesson's own, one per function of ``mistakes.py`` with the step's parameters (``mistake``).

``vision-lab lesson validate`` grades every mutant (:func:`lab.lessons.validate.mutation_report`) and
reports the checks that no mutant fails and the mutants no check catches; the grader compares a
student's result with the mutants' on a failed check to say which mistake it looks like.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import inspect
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

MutantKind = Literal["output", "inputs", "patch", "mistake"]


@dataclass(frozen=True)
class Mutant:
    """A wrong variant of a step's reference: ``name`` (how hints and reports call it), what a student whose
    result matches it is told, and how it is made from the reference function."""

    name: str
    kind: MutantKind
    hint: str
    make: Callable[[Callable[..., Any]], Callable[..., Any]]
    question: str = ""  # "of the reference transposed": how a hint that is not sure names it

    def __call__(self, reference: Callable[..., Any]) -> Callable[..., Any]:
        return self.make(reference)


class NotApplicable(Exception):
    """The mutant does not apply to this call (no square matrix to transpose, no mask argument)."""


# --- output transforms -------------------------------------------------------------------------------
def primary_array(value: Any) -> tuple[np.ndarray, Callable[[np.ndarray], Any]]:
    """The array a transform changes and how to put a changed one back: the value itself, or a typed
    value's first array field."""
    if isinstance(value, np.ndarray):
        return value, lambda array: array
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            field_value = getattr(value, f.name)
            if isinstance(field_value, np.ndarray):
                return field_value, lambda array, name=f.name: dataclasses.replace(value, **{name: array})
    raise NotApplicable("no array in the result")


def _numeric(array: np.ndarray) -> None:
    if array.dtype.kind not in "fiu" or array.size == 0:
        raise NotApplicable("not a numeric array")


def _transposed(array: np.ndarray) -> np.ndarray:
    if array.ndim < 2 or array.shape[-1] != array.shape[-2] or array.shape[-1] < 2:
        raise NotApplicable("not a square matrix")
    return np.swapaxes(array, -1, -2).copy()


def _inverse(array: np.ndarray) -> np.ndarray:
    _transposed(array)  # square
    _numeric(array)
    if array.dtype.kind != "f":
        raise NotApplicable("not a float matrix")
    try:
        return np.linalg.inv(array)
    except np.linalg.LinAlgError:
        raise NotApplicable("singular") from None


def _scaled(array: np.ndarray) -> np.ndarray:
    _numeric(array)
    if array.dtype.kind != "f":
        raise NotApplicable("not a float array")
    return array * 2.0


def _negated(array: np.ndarray) -> np.ndarray:
    _numeric(array)
    if array.dtype.kind == "u" or not np.any(array):
        raise NotApplicable("unsigned or zero")
    return -array


def _shifted(axis: int) -> Callable[[np.ndarray], np.ndarray]:
    def shift(array: np.ndarray) -> np.ndarray:
        if array.ndim == 0 or array.shape[axis] < 3 or (axis == -1 and array.ndim == 1):
            raise NotApplicable("too short an axis")
        if array.ndim >= 2 and array.shape[-1] == array.shape[-2] <= 4:
            raise NotApplicable("a small matrix: shifting its rows is no off-by-one")
        return np.roll(array, 1, axis=axis)
    return shift


def _float32(array: np.ndarray) -> np.ndarray:
    if array.dtype != np.float64:
        raise NotApplicable("not float64")
    return array.astype(np.float32)


def _reversed(array: np.ndarray) -> np.ndarray:
    if array.ndim < 2 or len(array) < 2:
        raise NotApplicable("not a stack of items")
    return array[::-1].copy()


_OUTPUT_TRANSFORMS: tuple[tuple[str, Callable[[np.ndarray], np.ndarray], str], ...] = (
    ("transposed", _transposed, "your result is the expected one transposed (rows and columns swapped): "
                                "check how you reshape or index it"),
    ("inverse", _inverse, "your matrix is the inverse of the expected one: it maps the other way (swap "
                          "source and target)"),
    ("scaled", _scaled, "your result is right up to a scale factor: normalise it as the task says"),
    ("negated", _negated, "your result is the expected one with the opposite sign"),
    ("shifted_first_axis", _shifted(0), "your result is the expected one shifted by one along its first "
                                        "axis: an off-by-one in an index or a range"),
    ("shifted_last_axis", _shifted(-1), "your result is the expected one shifted by one along its last axis: "
                                        "an off-by-one in an index or a range"),
    ("float32", _float32, "your result is float32 where float64 is expected: compute in float64"),
    ("reversed", _reversed, "your items are the expected ones in reverse order"),
)


def transform(name: str, array: np.ndarray) -> np.ndarray:
    """Output transform ``name`` applied to ``array`` (raises :class:`NotApplicable`)."""
    for entry_name, function, _ in _OUTPUT_TRANSFORMS:
        if entry_name == name:
            return function(array)
    raise NotApplicable(f"no output transform {name!r}")


def _output_mutant(name: str, transform: Callable[[np.ndarray], np.ndarray], hint: str) -> Mutant:
    def make(reference: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(reference)
        def mutant(*args: Any, **kwargs: Any) -> Any:
            array, put_back = primary_array(reference(*args, **kwargs))
            return put_back(transform(array))
        return mutant
    return Mutant(name, "output", hint, make, f"of the reference {name.replace('_', ' ')}")


# --- changed inputs ------------------------------------------------------------------------------------
def _array_of(value: Any) -> np.ndarray | None:
    if isinstance(value, np.ndarray):
        return value
    try:
        return primary_array(value)[0]
    except NotApplicable:
        return None


def _positional_names(reference: Callable[..., Any]) -> list[str]:
    return [p.name for p in inspect.signature(reference).parameters.values()
            if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]


def _bound(reference: Callable[..., Any], args: tuple, kwargs: dict[str, Any]) -> inspect.BoundArguments:
    bound = inspect.signature(reference).bind(*args, **kwargs)
    bound.apply_defaults()
    return bound


def _swapped(first: str, second: str) -> Mutant:
    def make(reference: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(reference)
        def mutant(*args: Any, **kwargs: Any) -> Any:
            bound = _bound(reference, args, kwargs)
            a, b = bound.arguments[first], bound.arguments[second]
            array_a, array_b = _array_of(a), _array_of(b)
            if type(a) is not type(b) or array_a is None or array_b is None or array_a.shape != array_b.shape:
                raise NotApplicable(f"{first} and {second} differ in type or shape")
            bound.arguments[first], bound.arguments[second] = b, a
            return reference(*bound.args, **bound.kwargs)
        return mutant
    return Mutant(f"swapped({first}, {second})", "inputs",
                  f"your result is what the computation gives with {first} and {second} swapped: check the "
                  f"order in which you use them", make, f"computed with {first} and {second} swapped")


def _mask_dropped(name: str) -> Mutant:
    def make(reference: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(reference)
        def mutant(*args: Any, **kwargs: Any) -> Any:
            bound = _bound(reference, args, kwargs)
            mask = bound.arguments[name]
            if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_ or mask.all():
                raise NotApplicable(f"{name} is no mask that leaves anything out")
            bound.arguments[name] = np.ones_like(mask)
            return reference(*bound.args, **bound.kwargs)
        return mutant
    return Mutant(f"mask_dropped({name})", "inputs",
                  f"your result is what the computation gives when every entry of {name} is True: use only "
                  f"the entries {name} selects", make, f"computed with every entry of {name} True")


# --- NumPy patched during the call ---------------------------------------------------------------------
_PATCH_LOCK = threading.RLock()  # np.argmin is process-wide: one patched call at a time


@contextlib.contextmanager
def _numpy_patched(replacements: dict[str, Callable[..., Any]], called: list[str]) -> Iterator[None]:
    originals = {name: getattr(np, name) for name in ("argmin", "argmax", *replacements)}

    def counting(name: str, function: Callable[..., Any]) -> Callable[..., Any]:
        def patched(*args: Any, **kwargs: Any) -> Any:
            called.append(name)
            return function(originals, *args, **kwargs)
        return patched

    with _PATCH_LOCK:
        for name, function in replacements.items():
            setattr(np, name, counting(name, function))
        try:
            yield
        finally:
            for name in replacements:
                setattr(np, name, originals[name])


def _last_extreme(which: str) -> Callable[..., Any]:
    """``np.argmin``/``np.argmax`` that returns the last of equal extremes instead of the first."""
    def last(originals: dict[str, Callable[..., Any]], a: Any, axis: int | None = None, **kwargs: Any) -> Any:
        array = np.asarray(a)
        if axis is None:
            flat = array.ravel()
            return flat.size - 1 - originals[which](flat[::-1], **kwargs)
        flipped = np.flip(array, axis=axis)
        return array.shape[axis] - 1 - originals[which](flipped, axis=axis, **kwargs)
    return last


def _patch_mutant(name: str, replacements: dict[str, Callable[..., Any]], hint: str) -> Mutant:
    def make(reference: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(reference)
        def mutant(*args: Any, **kwargs: Any) -> Any:
            called: list[str] = []
            with _numpy_patched(replacements, called):
                result = reference(*args, **kwargs)
            if not called:
                raise NotApplicable(f"the reference calls none of {sorted(replacements)}")
            return result
        return mutant
    return Mutant(name, "patch", hint, make)


_PATCHES: tuple[Mutant, ...] = (
    _patch_mutant("argmax_for_argmin", {"argmin": lambda o, *a, **k: o["argmax"](*a, **k)},
                  "your result picks the largest where the smallest is wanted (argmax for argmin?)"),
    _patch_mutant("argmin_for_argmax", {"argmax": lambda o, *a, **k: o["argmin"](*a, **k)},
                  "your result picks the smallest where the largest is wanted (argmin for argmax?)"),
    _patch_mutant("ties_other_way", {"argmin": _last_extreme("argmin"), "argmax": _last_extreme("argmax")},
                  "your result breaks ties the other way: on equal values the first one wins"),
)


# --- what a step gets ---------------------------------------------------------------------------------
def generic_mutants(reference: Callable[..., Any]) -> tuple[Mutant, ...]:
    """Every generic mutant of ``reference`` (those that turn out not to apply to a call raise
    :class:`NotApplicable` when called)."""
    positional = _positional_names(reference)
    mutants = [_output_mutant(*entry) for entry in _OUTPUT_TRANSFORMS]
    mutants += [_swapped(a, b) for i, a in enumerate(positional) for b in positional[i + 1:]]
    mutants += [_mask_dropped(name) for name in inspect.signature(reference).parameters]
    mutants += list(_PATCHES)
    return tuple(mutants)


def mistake_mutant(name: str, function: Callable[..., Any]) -> Mutant:
    """A function of the lesson's ``mistakes.py`` as a mutant (its hint: the lesson's, where one names it)."""
    return Mutant(name, "mistake", f"your result is what the known mistake {name!r} computes",
                  lambda reference: function)


__all__ = ["Mutant", "NotApplicable", "generic_mutants", "mistake_mutant", "primary_array",
           "transform"]
