"""Errors raised on bad input.

Every refusal names the offending field and the range it must lie in, so a
user (or an OPC UA client receiving the message as a status text) can act
on it without reading the code.
"""

from __future__ import annotations


class ValidationError(ValueError):
    """Input outside its allowed range.

    Attributes
    ----------
    field : str
        Name of the offending field, e.g. ``"mass"`` or ``"f"``.
    allowed : str
        Human-readable allowed range, e.g. ``"finite and >= 0 kg"``.
    """

    def __init__(self, field: str, allowed: str, detail: str = ""):
        self.field = field
        self.allowed = allowed
        self.detail = detail
        message = f"{field}: must be {allowed}"
        if detail:
            message += f" ({detail})"
        super().__init__(message)


class ValidationErrors(ValidationError):
    """Several refusals found in one validation pass, reported together.

    ``errors`` lists them (each a ``ValidationError``); ``field``, ``allowed``
    and ``detail`` are the first one's, and the message has one line each.
    """

    def __init__(self, errors):
        self.errors = list(errors)
        first = self.errors[0]
        self.field, self.allowed, self.detail = first.field, first.allowed, first.detail
        ValueError.__init__(self, "\n".join(str(error) for error in self.errors))


def raise_all(errors) -> None:
    """Raise nothing for no errors, the error itself for one, ``ValidationErrors`` else."""
    if len(errors) == 1:
        raise errors[0]
    if errors:
        raise ValidationErrors(errors)


def check_finite_range(field, values, low=None, high=None, *, low_open=False,
                       unit="", allow_nan=False):
    """Refuse ``values`` unless every element lies in [low, high] (or (low, high]).

    Parameters
    ----------
    field : str
        Field name used in the error message.
    values : array_like
        Values to check (any shape).
    low, high : float or None
        Bounds; ``None`` means unbounded.
    low_open : bool
        If true the lower bound is exclusive (``> low``).
    unit : str
        Unit appended to the bounds in the message.
    allow_nan : bool
        If true NaN is accepted (for optional attributes).
    """
    import numpy as np

    arr = np.asarray(values, dtype=np.float64)
    if arr.size and not allow_nan:
        # the common case, on every step of a run: two reductions (NaN fails both tests)
        smallest, largest = arr.min(), arr.max()
        if (np.isfinite(smallest) and np.isfinite(largest)
                and (low is None or (smallest > low if low_open else smallest >= low))
                and (high is None or largest <= high)):
            return arr
    suffix = f" {unit}" if unit else ""
    parts = ["finite"]
    if low is not None:
        parts.append(f"{'>' if low_open else '>='} {low:g}{suffix}")
    if high is not None:
        parts.append(f"<= {high:g}{suffix}")
    allowed = " and ".join(parts)
    finite = np.isfinite(arr)
    bad = ~finite
    if allow_nan:
        bad &= ~np.isnan(arr)
    checked = np.where(finite, arr, 0.0 if low is None else low + 1.0)
    if low is not None:
        bad |= finite & ((checked <= low) if low_open else (checked < low))
    if high is not None:
        bad |= finite & (checked > high)
    if bad.any():
        first = np.flatnonzero(bad.ravel())[0]
        raise ValidationError(
            field, allowed,
            f"got {arr.ravel()[first]!r} at index {first}; {int(bad.sum())} bad value(s)")
    return arr


def interruption(exc: BaseException) -> BaseException | None:
    """The ``KeyboardInterrupt`` (Ctrl-C, SIGINT) or ``SystemExit`` (a signal handler's
    ``sys.exit``) that ``exc`` is or was caused by; None if neither.

    A signal whose handler raises, landing while a numba kernel boxes its result,
    comes out of the call as ``SystemError("... returned a result with an exception
    set")`` with the handler's exception as its cause (6 of 100 SIGINTs sent into a
    tight loop of calls of a kernel returning a float and an array, numba 0.68 on
    CPython 3.11).
    """
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, (KeyboardInterrupt, SystemExit)):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def raise_if_interrupted(exc: BaseException) -> None:
    """Raise again (from ``exc``) the ``interruption`` that caused ``exc``, if any.

    Code that records a component's or a task's ``Exception`` as a failure
    calls this first, so that Ctrl-C or a stopping signal stops the run instead
    of becoming one more failed step.
    """
    found = interruption(exc)
    if found is not None:
        raise type(found)(*found.args) from exc
