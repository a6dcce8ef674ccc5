"""Registration of a group that mixes modalities (paper, closing discussion; issue 19).

The images are split into groups (modalities, e.g. T1- and T2-weighted) by a label per image.
Two strategies bring all N images into one frame, so that the Gaussian-mixture specificity
(:func:`itk_nrreval.specificity` with ``groups=``) can compare them:

``"joint"``
    Every image is registered to one reference -- the near-mean image of the reference
    group (by default the first group) -- with a metric that works across contrasts: an
    affine stage and a cubic B-spline stage, both with Mattes mutual information
    (``cross_metric``). Each image's error is its own.
``"per-group"``
    Each group is registered to its own reference (the group's near-mean image) with a
    same-contrast metric (``metric``); then ONE registration across contrasts (affine and
    B-spline, ``cross_metric``) links each other group's reference to the reference group's:
    ``L_g``, reference points -> group g's reference points. Image ``j`` of group ``g`` gets
    the transform ``T_j o L_g`` (reference point -> group reference point -> image point),
    so the result is one registration of all N images in the reference group's frame, and
    the link's error is shared by every image of group g.

Representation
--------------
Both strategies return one :class:`MultimodalResult` -- a :class:`RegistrationResult` with
one reference (the reference group's reference image, a training image: ``reference_index``)
and one transform per image mapping reference points to image points -- and are written
and added to a manifest as one registration each, like any other. The per-group link is
composed into the transforms of the other groups' images rather than written as the
manifest's ``frame_transform``: a manifest registration has one reference frame for all N
images and its ``frame_transform`` maps the common frame into that one frame, so it cannot
carry a link that applies to some images only; the composition is exactly the
``frame_transform`` construction applied per group. The links are also written
(``link_<group>.h5``) and listed in ``registration.json``, for inspection or reuse.

Metrics and defaults
--------------------
Within a group ``metric="correlation"`` (normalised correlation) is the default, not mean
squares: separate acquisitions of one modality differ by a global intensity scale (and a
bias field), which mean squares turns into spurious deformation (on the synthetic
populations of :mod:`data_synth`, elastix B-spline with mean squares left subjects *worse*
than the affine start, while correlation reached about 1.2 mm). Mattes mutual information
estimates a joint histogram from the sampled voxels, so the affine stages sample every voxel
by default (``affine_options={"sampling": 1.0}``; a quarter of a small image's coarse level
is too few samples for 50 bins).
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import time
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import SimpleITK as sitk

from ..._errors import InputError
from ..._output import claim_entries, write_json
from ..._progress import progress_bar
from ...io.transforms import flatten, write_transform
from ._common import check_choice, check_engine_options, input_settings, load_images, with_options
from ._elastix_worker import ElastixWorker, elastix_worker_for
from .affine import AffineOptions, affine_register, affine_to_reference, choose_reference
from .bspline import BSplineOptions, bspline_register, bspline_to_reference
from .result import RegistrationResult

__all__ = [
    "STRATEGIES",
    "MULTIMODAL_ENGINES",
    "MultimodalResult",
    "register_multimodal",
    "check_groups",
    "record_groups",
]

#: The strategies of :func:`register_multimodal`.
STRATEGIES = ("joint", "per-group")
#: Engines of the B-spline stages; the first is the default.
MULTIMODAL_ENGINES = ("elastix", "simpleitk")

_AFFINE_DEFAULTS = AffineOptions(sampling=1.0)


@dataclass(frozen=True)
class MultimodalResult(RegistrationResult):
    """A registration of a group mixing modalities: one frame, one transform per image.

    Everything of :class:`RegistrationResult` (``method="multimodal"``; ``transforms[i]``
    maps reference points to image ``i`` points, mm, LPS; ``reference`` is training image
    ``reference_index``, of the reference group), and:

    Attributes
    ----------
    strategy : {"joint", "per-group"}
    groups : tuple
        Each image's group label, as given.
    reference_group : hashable
        The group whose reference is the result's frame.
    group_references : dict
        Group -> index of its reference image ("joint": the reference group only).
    links : dict
        "per-group": group -> ``L_g``, reference points -> that group's reference points
        (every group but the reference group); "joint": empty. ``transforms[j]`` of an
        image of group g is ``T_j o L_g`` (flattened), ``T_j`` its registration to the
        group's reference.
    """

    strategy: str = "joint"
    groups: tuple = ()
    reference_group: Hashable = None
    group_references: Mapping[Hashable, int] = field(default_factory=dict)
    links: Mapping[Hashable, sitk.Transform] = field(default_factory=dict)

    def link_names(self) -> dict[Hashable, str]:
        """Group -> file name of its link transform (``link_<group>.h5``)."""
        out: dict[Hashable, str] = {}
        for k, g in enumerate(self.links):
            stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(g)) or f"group{k}"
            name = f"link_{stem}.h5"
            out[g] = name if name not in out.values() else f"link_{k}_{stem}.h5"
        return out

    def write(
        self, out: str | os.PathLike, *, names: Sequence[str] | None = None
    ) -> dict[str, Any]:
        """:meth:`RegistrationResult.write`, plus the links (``link_<group>.h5``).

        Returns
        -------
        dict
            ``{"reference": Path, "transforms": [Path, ...], "log": Path,
            "links": {group: Path}}``.
        """
        link_names = self.link_names()
        # every name claimed before any is written: a refused link leaves nothing behind
        claim_entries(
            out,
            [*link_names.values(), *self.file_names(names), *self.FILES],
            command="register",
        )
        paths = super().write(out, names=names)
        out = Path(out)
        links = {g: write_transform(self.links[g], out / name) for g, name in link_names.items()}
        log = json.loads(paths["log"].read_text())
        log["links"] = {str(g): p.name for g, p in links.items()}
        write_json(paths["log"], log)
        return {**paths, "links": links}

    def add_to_manifest(
        self,
        manifest: str | os.PathLike,
        name: str,
        *,
        out: str | os.PathLike,
        names: Sequence[str] | None = None,
        images: Sequence[str | os.PathLike] | None = None,
        labels: Sequence[str | os.PathLike] | None = None,
        parameters: Mapping[str, Any] | None = None,
    ) -> Path:
        """:meth:`RegistrationResult.add_to_manifest`, and the manifest's ``groups``.

        A manifest without ``groups`` gets this result's; one with other groups is refused.

        Raises
        ------
        InputError
            The manifest's ``groups`` differ from this result's.
        """
        _check_manifest_groups(manifest, self.groups)  # before writing anything
        path = super().add_to_manifest(
            manifest,
            name,
            out=out,
            names=names,
            images=images,
            labels=labels,
            parameters=parameters,
        )
        record_groups(path, self.groups)
        return path

    def manifest_parameters(self) -> dict[str, Any]:
        """Method, strategy, engine, seed, metrics, the group references and link files."""
        s = self.settings
        return {
            "method": "multimodal",
            "strategy": self.strategy,
            "engine": self.engine,
            "seed": s.get("seed"),
            "metric": s.get("metric"),
            "cross_metric": s.get("cross_metric"),
            "deformable": s.get("deformable"),
            "reference_group": str(self.reference_group),
            "group_references": {str(g): i for g, i in self.group_references.items()},
            "links": {str(g): n for g, n in self.link_names().items()},
        }


def _check_manifest_groups(manifest: str | os.PathLike, groups: Sequence[Hashable]) -> None:
    """Refuse `groups` for a manifest that lists other groups (a missing manifest is fine).

    Raises
    ------
    InputError
        The manifest's ``groups`` differ from `groups` (compared as strings).
    """
    from ...io.manifest import load_manifest  # noqa: PLC0415 - only needed here

    if not Path(manifest).exists():
        return
    old = load_manifest(manifest, check_files=False).groups
    mine = tuple(str(g) for g in groups)
    if old is not None and tuple(old) != mine:
        raise InputError(
            f"{manifest}: its groups {list(old)} differ from the registration's {list(mine)}"
        )


def record_groups(manifest: str | os.PathLike, groups: Sequence[Hashable]) -> None:
    """Write `groups` (as strings) into a manifest that has none; check them otherwise.

    Raises
    ------
    InputError
        The manifest's ``groups`` differ from `groups`.
    """
    from ...io.manifest import load_manifest, write_manifest  # noqa: PLC0415

    _check_manifest_groups(manifest, groups)
    m = load_manifest(manifest, check_files=False)
    if m.groups is None:
        write_manifest(dataclasses.replace(m, groups=tuple(str(g) for g in groups)), manifest)


def check_groups(groups, n: int) -> tuple:
    """`groups` as a tuple of labels, one per image, every group with >= 2 images.

    Raises
    ------
    InputError
        Not a sequence of str / int labels, a length other than `n`, or a group of one image
        (one line, naming the group).
    """
    if isinstance(groups, (str, bytes)) or not isinstance(groups, Sequence):
        raise InputError("groups: expected a list with one group label per image")
    labels = tuple(groups)
    bad = [g for g in labels if isinstance(g, bool) or not isinstance(g, (str, int))]
    if bad:
        raise InputError(f"groups: labels must be strings or integers, got {bad[0]!r}")
    if len(labels) != n:
        raise InputError(f"groups: {len(labels)} labels for {n} images")
    if len({str(g) for g in labels}) != len(set(labels)):
        raise InputError("groups: two labels differ only in type (e.g. 1 and '1')")
    small = [g for g in dict.fromkeys(labels) if labels.count(g) < 2]
    if small:
        raise InputError(f"groups: group {small[0]!r} has {labels.count(small[0])} image (needs 2)")
    return labels


def register_multimodal(
    images: Sequence[sitk.Image | str | os.PathLike],
    groups: Sequence[str | int],
    *,
    strategy: str = "joint",
    engine: str | None = None,
    reference_group: str | int | None = None,
    metric: str = "correlation",
    cross_metric: str = "mattes",
    options: Mapping[str, Any] | None = None,
    affine_options: Mapping[str, Any] | None = None,
    deformable: bool = True,
    out: str | os.PathLike | None = None,
    seed: int = 0,
    progress: bool = True,
    elastix_worker: ElastixWorker | None = None,
) -> MultimodalResult:
    """Register a group of images of several modalities into one frame.

    Parameters
    ----------
    images : sequence of sitk.Image or path, length n_images
        Scalar 2D or 3D images (grids may differ; registration works in physical space).
    groups : sequence of str or int, length n_images
        Each image's group (modality), e.g. ``["t1", "t1", "t2", "t2"]``; every group needs
        at least 2 images. The manifest's ``groups`` and :func:`itk_nrreval.specificity`'s.
    strategy : {"joint", "per-group"}
        ``"joint"``: every image to the reference with `cross_metric` (affine, B-spline).
        ``"per-group"``: each group to its own near-mean image with `metric`, then one
        `cross_metric` registration per other group linking its reference to the reference
        (module docstring).
    engine : {"elastix", "simpleitk"}, optional
        Engine of the B-spline stages (default elastix, run in a worker process); the affine
        stages are SimpleITK's.
    reference_group : str or int, optional
        The group whose near-mean image (after affine alignment within the group) is the
        frame; default the first image's group.
    metric : {"correlation", "mean_squares", "mattes"}
        Same-contrast similarity: reference choice, and the within-group registrations of
        ``"per-group"``.
    cross_metric : {"mattes", "correlation", "mean_squares"}
        Similarity across contrasts: every stage of ``"joint"`` and the links of
        ``"per-group"`` (Mattes mutual information by default).
    options : mapping, optional
        Fields of :class:`BSplineOptions` for the B-spline stages (not ``metric``: give
        `metric` / `cross_metric`).
    affine_options : mapping, optional
        Fields of :class:`AffineOptions` for the affine stages (not ``metric``); default
        ``sampling=1.0`` (module docstring).
    deformable : bool
        False: stop after the affine stages (the affine control of either strategy).
    out : path, optional
        Also write the result there (:meth:`MultimodalResult.write`).
    seed : int
        Seeds every random choice: the stages of image ``i`` use ``seed + i``, the link of
        the k-th other group ``seed + n_images + k``; the reference choice ``seed``.
    progress : bool
        Show progress bars on stderr.
    elastix_worker : ElastixWorker, optional
        A running worker to reuse (saves elastix's ~10 s start-up across calls).

    Returns
    -------
    MultimodalResult
        ``transforms[i]`` maps reference points to image ``i`` points (mm, LPS); the
        reference is image ``reference_index`` of the reference group.

    Raises
    ------
    InputError
        Bad `groups` (wrong length, a group of one image), unknown strategy / engine /
        metric / option, unreadable images, itk-elastix missing for engine ``"elastix"``.
    EngineError
        An engine failed (the message says which image).

    Examples
    --------
    >>> result = register_multimodal(paths, ["t1"] * 6 + ["t2"] * 6, strategy="per-group")
    ... # doctest: +SKIP
    >>> result.add_to_manifest("manifest.yaml", "per-group", out="per-group") # doctest: +SKIP
    """
    engine = _check_strategy_and_engine(strategy, engine)
    within, cross = _stage_options(
        engine,
        metric=metric,
        cross_metric=cross_metric,
        options=options,
        affine_options=affine_options,
    )
    imgs, paths = load_images(images)
    labels = check_groups(groups, len(imgs))
    ref_group, members = _group_members(labels, reference_group)
    with elastix_worker_for(elastix_worker, needed=deformable and engine == "elastix") as worker:
        started = time.perf_counter()
        run = _Run(
            imgs, seed=seed, engine=engine, worker=worker, progress=progress, deformable=deformable
        )
        registered = run.register(strategy, members, ref_group, within, cross)
    result = run.result(
        registered,
        strategy=strategy,
        labels=labels,
        reference_group=ref_group,
        paths=paths,
        metric=metric,
        cross_metric=cross_metric,
        within=within,
        started=started,
    )
    if out is not None:
        result.write(out)
    return result


@dataclass(frozen=True)
class _StageOptions:
    """The options of one metric's stages: the affine, then the B-spline."""

    affine: AffineOptions
    bspline: BSplineOptions


@dataclass(frozen=True)
class _GroupReference:
    """A group's reference image and the affines that chose it."""

    #: The reference's index among all images.
    index: int
    #: Per image of the group (in the group's order), reference -> image affine: a start
    #: for the registrations to the reference.
    affines: list[sitk.Transform]


def _check_strategy_and_engine(strategy: str, engine: str | None) -> str:
    """The engine (default elastix) once `strategy` and `engine` are known ones (InputError)."""
    check_choice("strategy", strategy, STRATEGIES)
    engine = MULTIMODAL_ENGINES[0] if engine is None else engine
    check_choice("engine", engine, MULTIMODAL_ENGINES)
    return engine


def _stage_options(
    engine: str,
    *,
    metric: str,
    cross_metric: str,
    options: Mapping[str, Any] | None,
    affine_options: Mapping[str, Any] | None,
) -> tuple[_StageOptions, _StageOptions]:
    """The within-group (`metric`) and the cross-contrast (`cross_metric`) stage options,
    checked (InputError before any work)."""
    for what, given in (("options", options), ("affine_options", affine_options)):
        if given and "metric" in given:
            raise InputError(f"{what}: give the metric as metric= or cross_metric=")
    aff_within = with_options(_AFFINE_DEFAULTS, affine_options, what="affine")
    aff_within = dataclasses.replace(aff_within, metric=metric)
    aff_within.check()
    aff_cross = dataclasses.replace(aff_within, metric=cross_metric)
    aff_cross.check()
    bs_within = dataclasses.replace(
        with_options(BSplineOptions(), options, what="pairwise"), metric=metric
    )
    bs_within.check()
    bs_cross = dataclasses.replace(bs_within, metric=cross_metric)
    bs_cross.check()
    check_engine_options("multimodal", engine, bs_within)
    return _StageOptions(aff_within, bs_within), _StageOptions(aff_cross, bs_cross)


def _group_members(
    labels: tuple, reference_group: Hashable | None
) -> tuple[Hashable, dict[Hashable, list[int]]]:
    """The reference group (default the first image's) and each group's image indices, the
    groups in order of first appearance."""
    order = list(dict.fromkeys(labels))
    ref_group = labels[0] if reference_group is None else reference_group
    if ref_group not in order:
        raise InputError(
            f"reference_group: {ref_group!r} is not one of the groups {', '.join(map(repr, order))}"
        )
    return ref_group, {g: [i for i, lab in enumerate(labels) if lab == g] for g in order}


def _without_metric(options) -> dict[str, Any]:
    """The options as a dict, without the metric (set per stage by metric / cross_metric)."""
    return {k: v for k, v in dataclasses.asdict(options).items() if k != "metric"}


class _Run:
    """The images, engine and seed of one :func:`register_multimodal` call, and its steps."""

    def __init__(
        self, imgs, *, seed: int, engine: str, worker, progress: bool, deformable: bool
    ) -> None:
        self.imgs, self.seed, self.engine = imgs, seed, engine
        self.worker, self.progress, self.deformable = worker, progress, deformable

    def register(
        self,
        strategy: str,
        members: Mapping[Hashable, list[int]],
        reference_group: Hashable,
        within: _StageOptions,
        cross: _StageOptions,
    ) -> tuple[dict[Hashable, _GroupReference], list[sitk.Transform], dict]:
        """The references chosen, the transforms and the links (none for "joint") of
        `strategy`: "joint" registers every image to the reference group's reference,
        "per-group" each group to its own and then links the references."""
        chosen_for = [reference_group] if strategy == "joint" else list(members)
        references = self.references(members, chosen_for, within)
        if strategy == "joint":
            reference = references[reference_group]
            return references, self.joint(members[reference_group], reference, cross), {}
        transforms, links = self.per_group(members, references, reference_group, within, cross)
        return references, transforms, links

    def result(
        self,
        registered: tuple[dict[Hashable, _GroupReference], list[sitk.Transform], dict],
        *,
        strategy: str,
        labels: tuple,
        reference_group: Hashable,
        paths: list[str | None],
        metric: str,
        cross_metric: str,
        within: _StageOptions,
        started: float,
    ) -> MultimodalResult:
        """The :class:`MultimodalResult` of what :meth:`register` gave, with the settings
        ``registration.json`` records (`paths` as :func:`load_images` gives them, `started`
        the ``time.perf_counter()`` the run started at)."""
        references, transforms, links = registered
        r0 = references[reference_group].index
        group_refs = {g: chosen.index for g, chosen in references.items()}
        settings = {
            "method": "multimodal",
            "strategy": strategy,
            "engine": self.engine,
            **input_settings(seed=self.seed, paths=paths),
            "groups": [str(g) for g in labels],
            "reference_group": str(reference_group),
            "reference_choice": "near-mean of the reference group",
            "group_references": {str(g): i for g, i in group_refs.items()},
            "metric": metric,
            "cross_metric": cross_metric,
            "deformable": bool(self.deformable),
            "affine_options": _without_metric(within.affine),
            "options": _without_metric(within.bspline),
        }
        return MultimodalResult.from_transforms(
            self.imgs,
            transforms,
            reference=self.imgs[r0],
            reference_index=r0,
            settings=settings,
            started=started,
            method="multimodal",
            engine=self.engine if self.deformable else "simpleitk",
            strategy=strategy,
            groups=labels,
            reference_group=reference_group,
            group_references=group_refs,
            links=links,
        )

    def references(
        self,
        members: Mapping[Hashable, list[int]],
        groups: Sequence[Hashable],
        within: _StageOptions,
    ) -> dict[Hashable, _GroupReference]:
        """Each of `groups`' near-mean image, after affine alignment within the group with
        the within-group metric (seeded with ``seed``)."""
        chosen = {}
        for g in groups:
            local, affines, _ = choose_reference(
                [self.imgs[i] for i in members[g]],
                "near-mean",
                options=within.affine,
                seed=self.seed,
                progress=self.progress,
            )
            chosen[g] = _GroupReference(members[g][local], affines)
        return chosen

    def joint(
        self, reference_members: list[int], reference: _GroupReference, cross: _StageOptions
    ) -> list[sitk.Transform]:
        """ "joint": every image registered to `reference` with the cross-contrast metric; the
        reference group's images (`reference_members`) start from the reference choice's
        affines."""
        start: list[sitk.Transform | None] = [None] * len(self.imgs)
        for i, t in zip(reference_members, reference.affines, strict=True):
            start[i] = t
        return self.stage(list(range(len(self.imgs))), reference.index, cross, start, desc="joint")

    def per_group(
        self,
        members: Mapping[Hashable, list[int]],
        references: Mapping[Hashable, _GroupReference],
        reference_group: Hashable,
        within: _StageOptions,
        cross: _StageOptions,
    ) -> tuple[list[sitk.Transform], dict[Hashable, sitk.Transform]]:
        """ "per-group": each group registered to its reference (within-group metric), then
        each other group's reference linked to the reference group's (cross-contrast metric).

        Returns the transforms, reference group's reference -> image (``T_j o L_g``), and
        the links ``L_g`` per other group (the k-th seeded with ``seed + n_images + k``).
        """
        transforms = [sitk.Transform()] * len(self.imgs)
        for g, indices in members.items():
            ref_g = references[g]
            mine = self.stage(indices, ref_g.index, within, ref_g.affines, desc=f"{g}")
            for i, t in zip(indices, mine, strict=True):
                transforms[i] = t
        r0 = references[reference_group].index
        links: dict[Hashable, sitk.Transform] = {}
        others = [g for g in members if g != reference_group]
        for k, g in enumerate(progress_bar(others, desc="links", enabled=self.progress)):
            rg = references[g].index
            links[g] = self.link(
                r0,
                rg,
                cross,
                len(self.imgs) + k,
                what=f"the link of group {g!r} (image {rg} to image {r0})",
            )
            for i in members[g]:
                transforms[i] = flatten(sitk.CompositeTransform([transforms[i], links[g]]))
        return transforms, links

    def stage(
        self,
        indices: list[int],
        reference: int,
        options: _StageOptions,
        initial: Sequence[sitk.Transform | None],
        *,
        desc: str,
    ) -> list[sitk.Transform]:
        """Images `indices` registered to image `reference` (one of them): affine, B-spline.

        `initial` (one per index, or None entries) starts the affines; image ``i`` uses the
        seed ``seed + i``.
        """
        imgs = [self.imgs[i] for i in indices]
        local = indices.index(reference)
        ref = self.imgs[reference]
        affines = affine_to_reference(
            imgs,
            ref,
            options=options.affine,
            seed=self.seed,
            reference_index=local,
            initial=initial,
            progress=self.progress,
            numbers=indices,
            desc=f"affine {desc}",
        )
        if not self.deformable:
            return list(affines)
        transforms, _ = bspline_to_reference(
            imgs,
            ref,
            affines,
            options=options.bspline,
            engine=self.engine,
            seed=self.seed,
            reference_index=local,
            progress=self.progress,
            worker=self.worker,
            numbers=indices,
            desc=f"B-spline {desc}",
        )
        return [flatten(t) for t in transforms]

    def link(
        self, reference: int, other: int, options: _StageOptions, number: int, *, what: str
    ) -> sitk.Transform:
        """Image `reference`'s points -> image `other`'s points (affine, B-spline).

        Seeded with ``seed + number``; `what` names the job in error messages.
        """
        ref, img = self.imgs[reference], self.imgs[other]
        a = affine_register(ref, img, options=options.affine, seed=self.seed + number)
        if not self.deformable:
            return a
        transform, _ = bspline_register(
            ref,
            img,
            a,
            options=options.bspline,
            engine=self.engine,
            seed=self.seed + number,
            worker=self.worker,
            what=what,
        )
        return flatten(transform)
