"""Every option of one image pair's chain as one object: :class:`PairSettings`, the single
home of :func:`plenocl.process_pair`'s defaults, read from and written to plain nested
dicts (an experiment file's sections, docs/batch.md). Its reconstruction's defaults are
:class:`~plenocl.reconstruction.ReconstructionSettings`' own, :func:`plenocl.reconstruct`'s."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

from ..options import field_names, from_table, refuse_unknown, to_table
from ..piv.imagefit import ImageFitSettings
from ..piv.settings import PIVSettings
from ..projection.projector import DEFAULT_LENS_WEIGHTS
from ..reconstruction import ReconstructionSettings
from .mte import MTESettings

#: The parts of a pair's settings, as the sections of a document.
PARTS = ("reconstruction", "piv", "mte", "particles", "image_fit")


@dataclass(frozen=True)
class PairSettings:
    """Every option of :func:`plenocl.process_pair`, checked once by its parts.

    Attributes
    ----------
    reconstruction
        Both exposures' reconstruction (:class:`~plenocl.reconstruction.ReconstructionSettings`;
        by default its defaults, as :func:`plenocl.reconstruct`'s: coarse-to-fine MLEM on
        3 x 3 lateral sub-voxels per voxel, docs/design.md §6.5).
    piv
        The correlation (:class:`~plenocl.piv.PIVSettings`; by default the windows are
        fitted to the volume).
    mte
        Motion-tracking enhancement (:class:`~plenocl.pipeline.MTESettings`; off by
        default, ``cycles=0``).
    particles
        Refine the correlation's field with the volumes' matched particle pairs
        (docs/design.md §7.1).
    image_fit
        Fit those particles to the raw images first (docs/design.md §7.2) with these
        :class:`~plenocl.piv.imagefit.ImageFitSettings`; ``None``: off. Made with
        ``True`` or ``False``, it holds the default settings or ``None``.
    """

    reconstruction: ReconstructionSettings = field(default_factory=ReconstructionSettings)
    piv: PIVSettings = field(default_factory=PIVSettings)
    mte: MTESettings = field(default_factory=MTESettings)
    particles: bool = True
    image_fit: ImageFitSettings | None = field(default_factory=ImageFitSettings)

    def __post_init__(self) -> None:
        if isinstance(self.image_fit, bool):
            object.__setattr__(self, "image_fit", ImageFitSettings() if self.image_fit else None)
        for name, cls in (("reconstruction", ReconstructionSettings), ("piv", PIVSettings),
                          ("mte", MTESettings), ("image_fit", ImageFitSettings)):
            value = getattr(self, name)
            if not (isinstance(value, cls) or (name == "image_fit" and value is None)):
                raise TypeError(f"PairSettings.{name} must be a {cls.__name__}, got "
                                f"{type(value).__name__}")
        if not isinstance(self.particles, bool):
            raise ValueError(f"PairSettings.particles must be true or false, got "
                             f"{self.particles!r}")

    def with_named_weights(self) -> PairSettings:
        """These settings with the reconstruction's lens weights named: ``None`` (the
        projector's own) becomes the projector's default,
        :data:`~plenocl.projection.projector.DEFAULT_LENS_WEIGHTS`. A stored result's
        digest then names the weights that made its volumes, and a rerun after the
        default changed redoes them instead of keeping the other weights' volumes."""
        if self.reconstruction.lens_weights is not None:
            return self
        return replace(self, reconstruction=replace(self.reconstruction,
                                                    lens_weights=DEFAULT_LENS_WEIGHTS))

    def to_dict(self, none=None) -> dict:
        """The settings as nested plain dicts, the shape :meth:`from_dict` reads: one
        table per part, ``particles`` and ``image_fit`` with an ``enabled`` key. A
        reconstruction that starts from a volume has no such form (ValueError).
        ``none``: what an option set to ``None`` becomes (``plenocl.options.NONE``,
        ``"none"``, for a TOML file, which has no null)."""
        start = self.reconstruction.start
        if not isinstance(start, str):
            raise ValueError("PairSettings.to_dict: the reconstruction starts from a volume, "
                             "which a settings document cannot hold")
        fit = self.image_fit
        return {"reconstruction": to_table(self.reconstruction, none=none),
                "piv": to_table(self.piv, none=none), "mte": to_table(self.mte, none=none),
                "particles": {"enabled": self.particles},
                "image_fit": {"enabled": fit is not None,
                              **to_table(fit if fit is not None else ImageFitSettings(),
                                         none=none)}}

    @classmethod
    def from_dict(cls, doc: Mapping, source: str = "settings") -> PairSettings:
        """Settings from nested dicts (:meth:`to_dict`'s shape; every part and key
        optional, the defaults filling in). ``particles`` and ``image_fit`` may also be
        plain ``true``/``false``.

        Raises
        ------
        ValueError
            An unknown part or key (named, with those allowed) or a bad value, the
            message starting with ``source`` (e.g. the file's path).
        """
        if not isinstance(doc, Mapping):
            raise ValueError(f"{source}: pair settings must be a table, got {doc!r}")
        refuse_unknown(doc, PARTS, lambda bad: f"{source}: unknown section(s) {bad}; the "
                       f"pair settings are {list(PARTS)}")
        return cls(
            reconstruction=from_table(ReconstructionSettings, doc.get("reconstruction", {}),
                                      f"{source}: [reconstruction]"),
            piv=from_table(PIVSettings, doc.get("piv", {}), f"{source}: [piv]"),
            mte=from_table(MTESettings, doc.get("mte", {}), f"{source}: [mte]"),
            particles=_enabled(doc.get("particles", True), f"{source}: [particles]", []),
            image_fit=_image_fit(doc.get("image_fit", True), f"{source}: [image_fit]"))


def _enabled(value, where: str, allowed: list[str]) -> bool:
    """A part's on/off switch: ``true``/``false``, or a table's ``enabled`` key."""
    if isinstance(value, Mapping):
        keys = ["enabled", *allowed]
        refuse_unknown(value, keys, lambda bad: f"{where}: unknown key(s) {bad}; it takes {keys}")
        value = value.get("enabled", True)
    if not isinstance(value, bool):
        raise ValueError(f"{where} enabled must be true or false, got {value!r}")
    return value


def _image_fit(value, where: str) -> ImageFitSettings | None:
    """The image fit's part: off, or its settings (a table of them, ``enabled`` aside)."""
    if not _enabled(value, where, field_names(ImageFitSettings)):
        return None
    table = {k: v for k, v in value.items() if k != "enabled"} if isinstance(value, Mapping) \
        else {}
    return from_table(ImageFitSettings, table, where)
