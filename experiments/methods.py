"""What a report row is: one `Method`, used by the workflow grid, the edit step's parameters, the report's
rows, marks and labels.

    Method.parse("IN2N")        Iterative Dataset Update on a single field: Instruct-NeRF2NeRF (DF, SA, CCI off)
    Method.parse("DualNeRF")    IDU with the dual field (DF), simulated annealing (SA) and the CLIP
                                consistency indicator (CCI): the full method
    Method.parse("DF+SA")       any "+"-combination of DF, SA and CCI ("baseline": none of them)
    Method.parse("per-frame")   the per-frame InstructPix2Pix baseline: no IDU, its own kind
    ORIGINAL                    the unedited scene (the report's first row)

A method has a kind (IDU, PER_FRAME, ORIGINAL) and, for IDU methods only, the three flags; its label is
the name the workflow used, so step labels, report rows and `--reference` read as the workflow wrote them.
The older workflow syntax `variants = [[DF, SA, CCI], ...]` becomes method names in one place,
`names_from_variants` (labels "baseline", "DF", "DF+SA", ...: the labels those rows always had).
"""
from __future__ import annotations

from dataclasses import dataclass

IDU = "idu"
PER_FRAME = "per-frame"
ORIGINAL_KIND = "original"
KINDS = (IDU, PER_FRAME, ORIGINAL_KIND)
FLAGS = ("DF", "SA", "CCI")                      # dual_field, annealing, consistency, in this order
# Names of IDU methods that are not a combination of FLAGS.
NAMED = {"IN2N": (False, False, False), "DualNeRF": (True, True, True), "baseline": (False, False, False)}
# The edit stage's parameters that a method sets (EditParams; managed by the workflow).
EDIT_PARAMS = ("dual_field", "annealing", "consistency")


class MethodError(ValueError):
    """A method name or [DF, SA, CCI] row that names no method; the message lists the valid ones."""

    user_error = True


@dataclass(frozen=True)
class Method:
    label: str
    kind: str = IDU
    dual_field: bool = False
    annealing: bool = False
    consistency: bool = False

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"method kind must be one of {KINDS}, got {self.kind!r}")
        if self.kind != IDU and (self.dual_field or self.annealing or self.consistency):
            raise ValueError(f"{self.kind} method '{self.label}' cannot switch on DF, SA or CCI")

    @classmethod
    def idu(cls, dual_field: bool, annealing: bool, consistency: bool, label: str | None = None) -> Method:
        flags = (bool(dual_field), bool(annealing), bool(consistency))
        return cls(combination_label(*flags) if label is None else label, IDU, *flags)

    @classmethod
    def per_frame(cls, label: str = PER_FRAME) -> Method:
        return cls(label, PER_FRAME)

    @classmethod
    def original(cls, label: str = "Original scene") -> Method:
        return cls(label, ORIGINAL_KIND)

    @classmethod
    def parse(cls, name: str) -> Method:
        """A method from its workflow name (see the module docstring); MethodError for anything else."""
        if name == PER_FRAME:
            return cls.per_frame()
        if name in NAMED:
            return cls.idu(*NAMED[name], label=name)
        parts = name.split("+")
        if not set(parts) <= set(FLAGS) or len(set(parts)) != len(parts):
            raise MethodError(f"unknown method '{name}'; methods are '{PER_FRAME}', 'IN2N', 'DualNeRF', "
                              f"'baseline' or a '+'-combination of {', '.join(FLAGS)} (e.g. 'DF+SA').")
        return cls.idu(*(flag in parts for flag in FLAGS))

    @property
    def is_original(self) -> bool:
        return self.kind == ORIGINAL_KIND

    @property
    def is_per_frame(self) -> bool:
        return self.kind == PER_FRAME

    @property
    def flags(self) -> tuple[bool, bool, bool] | None:
        """(DF, SA, CCI) of an IDU method; None for the per-frame baseline and the unedited scene."""
        return (self.dual_field, self.annealing, self.consistency) if self.kind == IDU else None

    def edit_params(self) -> dict[str, bool]:
        """The edit stage's parameters for this IDU method."""
        if self.kind != IDU:
            raise ValueError(f"{self.kind} method '{self.label}' runs no edit stage")
        return dict(zip(EDIT_PARAMS, self.flags))

    def marks(self) -> tuple[str, str, str]:
        """The report's DF / SA / CCI columns: ✓ / ✗ for IDU methods, "–" (not applicable) for the
        per-frame baseline, empty for the unedited scene."""
        if self.kind == IDU:
            return tuple("✓" if flag else "✗" for flag in self.flags)
        return ("–",) * 3 if self.kind == PER_FRAME else ("",) * 3


ORIGINAL = Method.original()


def combination_label(dual_field: bool, annealing: bool, consistency: bool) -> str:
    """"DF+SA", ...; "baseline" with every flag off (the single-field IN2N row of the ablation)."""
    on = [name for name, flag in zip(FLAGS, (dual_field, annealing, consistency)) if flag]
    return "+".join(on) if on else "baseline"


def names_from_variants(rows) -> list[str]:
    """The older `variants = [[DF, SA, CCI], ...]` rows as method names (labels unchanged)."""
    if not isinstance(rows, list) or not rows:
        raise MethodError("[workflow] variants must be a non-empty list of [DF, SA, CCI] booleans; "
                          "better, give methods = [\"IN2N\", \"DF+SA\", \"DualNeRF\", ...].")
    names = []
    for row in rows:
        if not (isinstance(row, list) and len(row) == 3 and all(isinstance(v, bool) for v in row)):
            raise MethodError(f"variant {row!r} must be three booleans [DF, SA, CCI].")
        names.append(combination_label(*row))
    return names
