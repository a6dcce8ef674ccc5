"""The result of registering a group: transforms reference -> image, reference, settings."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import SimpleITK as sitk

from ..._errors import InputError
from ..._output import atomic_path, claim_entries, write_json
from ...io.transforms import write_transform
from ._common import resample

__all__ = ["RegistrationResult"]


@dataclass(frozen=True)
class RegistrationResult:
    """What :func:`register` returns: the registration of N images to one reference frame.

    Attributes
    ----------
    method : str
        ``"affine"``, ``"fluid"``, ``"pairwise"``, ``"groupwise"`` or ``"multimodal"``
        (:func:`~itk_nrreval.experiments.registration.register_multimodal`).
    engine : str
        The engine that produced the non-affine part (``"simpleitk"``, ``"elastix"``, ...).
    transforms : tuple of sitk.Transform, length n_images
        Image ``i``'s transform, reference points -> image ``i`` points (mm, LPS). Affine:
        ``AffineTransform``; fluid: ``CompositeTransform([A_i, field_i])``; pairwise
        (elastix): one ``DisplacementFieldTransform`` on the reference grid (affine
        included); pairwise (SimpleITK) and groupwise: ``CompositeTransform`` of the affine
        and the B-spline(s) (elastix-stack: ``[A_i, B_i]``); multimodal: see
        :class:`~itk_nrreval.experiments.registration.MultimodalResult`.
    reference : sitk.Image
        The reference image; its grid is the registration's frame.
    reference_index : int or None
        Index of the training image used as reference, or None (groupwise mean, or an image
        that is not one of the inputs).
    resampled : tuple of sitk.Image, length n_images
        Each image on the reference grid as the engine itself resampled it (elastix: its
        own result image; SimpleITK: ``sitk.Resample`` through ``transforms[i]``), linear
        interpolation, 0 outside. elastix-stack: elastix's registered slice ``i``, i.e. the
        image resampled through ``A_i`` and then through ``B_i`` (two interpolations).
    settings : dict
        Method, engine, seed, reference choice, affine and method options (JSON-ready).
    seconds : float
        Wall time of the registration.
    """

    method: str
    engine: str
    transforms: tuple[sitk.Transform, ...]
    reference: sitk.Image
    reference_index: int | None
    resampled: tuple[sitk.Image, ...]
    settings: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0

    @classmethod
    def from_transforms(
        cls,
        images: Sequence[sitk.Image],
        transforms: Sequence[sitk.Transform],
        *,
        reference: sitk.Image,
        reference_index: int | None,
        settings: dict[str, Any],
        started: float,
        resampled: Sequence[sitk.Image] | None = None,
        **fields: Any,
    ):
        """The result of registering `images`: one transform each, reference -> image.

        Parameters
        ----------
        images : sequence of sitk.Image, length n_images
            The registered images.
        transforms : sequence of sitk.Transform, length n_images
            Reference points -> image ``i`` points (mm, LPS).
        reference : sitk.Image, keyword-only
            The reference; its grid is the frame.
        reference_index : int or None, keyword-only
            As the attribute.
        settings : dict, keyword-only
            As the attribute; refused (TypeError) here unless JSON-ready, not at write time.
        started : float, keyword-only
            ``time.perf_counter()`` when the registration started: `seconds` runs from it to
            now, after the resampling.
        resampled : sequence of sitk.Image, length n_images, optional
            The engine's own resampled images; default each image resampled through its
            transform on the reference grid (linear, 0 outside).
        **fields
            The other fields of `cls` (``method``, ``engine``, and a subclass's own).

        Returns
        -------
        RegistrationResult
            Of type `cls`, ``seconds`` the wall time since `started`.
        """
        if resampled is None:
            resampled = [
                resample(im, reference, t) for im, t in zip(images, transforms, strict=True)
            ]
        seconds = time.perf_counter() - started
        json.dumps(settings)  # settings must stay JSON-ready
        return cls(
            transforms=tuple(transforms),
            reference=reference,
            reference_index=reference_index,
            resampled=tuple(resampled),
            settings=settings,
            seconds=seconds,
            **fields,
        )

    @property
    def n_images(self) -> int:
        return len(self.transforms)

    def write(
        self, out: str | os.PathLike, *, names: Sequence[str] | None = None
    ) -> dict[str, Any]:
        """Write the transforms (``.h5``), the reference image and ``registration.json``.

        Parameters
        ----------
        out : path
            Folder, created if needed.
        names : sequence of str, optional
            A stem per image for the transform files (default ``image000`` ...).

        Returns
        -------
        dict
            ``{"reference": Path, "transforms": [Path, ...], "log": Path}``.

        Raises
        ------
        InputError
            A file of one of these names is in `out` and was not written by the toolkit
            (nothing is written; files of other names in `out` are left alone).
        """
        files = self.file_names(names)
        out = claim_entries(out, [*files, *self.FILES], command="register")
        paths = [write_transform(t, out / f) for t, f in zip(self.transforms, files, strict=True)]
        reference = out / self.FILES[0]
        with atomic_path(reference) as tmp:
            sitk.WriteImage(self.reference, str(tmp))
        log = out / self.FILES[1]
        write_json(
            log,
            {
                **self.settings,
                "reference_index": self.reference_index,
                "seconds": round(self.seconds, 3),
                "reference": reference.name,
                "transforms": [p.name for p in paths],
                "convention": "each transform maps reference points to image points (mm, LPS)",
            },
        )
        return {"reference": reference, "transforms": paths, "log": log}

    #: The files :meth:`write` writes beside the transforms.
    FILES = ("reference.nii.gz", "registration.json")

    def file_names(self, names: Sequence[str] | None = None) -> list[str]:
        """The transform files' names :meth:`write` gives: ``000_<stem>.h5`` ... (default
        stems ``image000`` ...)."""
        names = [f"image{i:03d}" for i in range(self.n_images)] if names is None else list(names)
        if len(names) != self.n_images:
            raise InputError(f"names: {len(names)} given for {self.n_images} transforms")
        return [f"{i:03d}_{stem}.h5" for i, stem in enumerate(names)]

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
        """:meth:`write` into `out`, then add the result to a manifest file as `name`.

        Parameters
        ----------
        manifest : path
            The manifest (YAML), created when missing (then `images` is required).
        name : str
            The registration's name there (an existing one of that name is replaced).
        out : path
            The folder the transforms and reference are written to.
        names : sequence of str, optional
            A stem per image for the transform files (:meth:`write`).
        images, labels : sequence of path, optional
            The manifest's images / labels (:func:`itk_nrreval.io.manifest.add_registration`).
        parameters : mapping, optional
            Settings recorded in the manifest (default :meth:`manifest_parameters`).

        Returns
        -------
        Path
            `manifest`.
        """
        from ...io.manifest import add_registration, check_rewritable  # noqa: PLC0415

        check_rewritable(manifest)  # before any transform is written
        written = self.write(out, names=names)
        return add_registration(
            manifest,
            name,
            reference=written["reference"],
            transforms=[str(p) for p in written["transforms"]],
            reference_index=self.reference_index,
            images=images,
            labels=labels,
            parameters=self.manifest_parameters() if parameters is None else parameters,
        )

    def manifest_parameters(self) -> dict[str, Any]:
        """The settings worth recording in a manifest: method, engine, seed, reference choice."""
        keys = ("method", "engine", "seed", "reference_choice")
        return {k: self.settings[k] for k in keys if self.settings.get(k) is not None}
