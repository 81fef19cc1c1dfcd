"""The error a part's configuration object (``LandingConfig``, ``PipelineConfig``, ``LinkConfig``,
...) raises when one of its fields holds a value the object refuses.

Each part keeps its own invariants in its ``__post_init__``: tests, replay, the evaluation and the
simulator build these objects directly, so they must refuse bad values themselves. The settings
do not repeat those rules: ``companion.config.compose`` builds the parts while it validates a
configuration and turns a ``FieldError`` into a ``ConfigError`` that names the settings key the
field came from (``controller.descend_alt_m``), using its table from field to key. The error
therefore says which field, what is wrong and the value, apart, so that the key can be put in the
field's place. It is a ``ValueError``, as the parts raised before.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

#: ``FieldError(value=NO_VALUE)``: the message shows no value (a rule between fields says its own).
NO_VALUE: Any = object()


class FieldError(ValueError):
    """``owner``'s field ``field`` holds a value its object refuses.

    ``problem`` says what is wrong, after the field's name (``"must be > 0"``); a rule between
    fields refers to another field of the same object as ``{name}``, listed in ``refs``, so that
    each can be renamed (``named``). ``value`` is appended as ``", got <repr>"`` unless NO_VALUE.
    """

    def __init__(self, owner: str, field: str, problem: str, value: Any = NO_VALUE,
                 refs: Iterable[str] = ()) -> None:
        self.owner, self.field, self.problem, self.value = owner, field, problem, value
        self.refs = tuple(refs)
        super().__init__(f"{owner} {self.named({})}")

    def named(self, names: Mapping[str, str]) -> str:
        """The message with each field called by ``names`` (field -> name; a field missing from
        it keeps its own name): ``"controller.land_alt_m must be >= 0, got -1.0"``."""
        text = self.problem
        for ref in self.refs:
            text = text.replace("{" + ref + "}", names.get(ref, ref))
        tail = "" if self.value is NO_VALUE else f", got {self.value!r}"
        return f"{names.get(self.field, self.field)} {text}{tail}"


def require(ok: bool, owner: str, field: str, problem: str, value: Any = NO_VALUE,
            refs: Iterable[str] = ()) -> None:
    """Raise ``FieldError(owner, field, problem, value, refs)`` unless ``ok``."""
    if not ok:
        raise FieldError(owner, field, problem, value, refs)


__all__ = ["FieldError", "NO_VALUE", "require"]
