"""Is the verdict right? Its decided pairs against the true correspondence error.

Each case is one generated population (known true transforms) registered several ways; every
registration's true mean correspondence error (mm,
:func:`itk_nrreval.experiments.correspondence.correspondence_error`) is computed beside the
evaluation, and the verdict's decided pairs
(:attr:`itk_nrreval.evaluation.Verdict.decisions`) are judged against it. For every pair of
registrations whose true errors differ by more than ``MARGIN`` (10% of the smaller), the
verdict is *right* (it decides the lower-error one better), *wrong* (the other way) or
*open* (it decides nothing). Pairs closer than that are near-ties: counted apart, decided or
open.

Cases (2D, N = 12, M = ``N_SAMPLES``, unless said):

* ``demo``: the demo's five registrations (:func:`itk_nrreval.experiments.demo.run_demo`, phantom);
* ``cheat``: the demo's registrations plus Rohlfing's class-matching cheat
  (:func:`bench_cheat.add_cheat`);
* ``sweep_<case>``: the 2D sweeps of ``bench_sweeps.CASES`` (demons field / update smoothing,
  B-spline grid spacing, bending weight; phantom and MNI);
* ``unseen_<case>``: the registrations of ``sweep_<case>`` (made on T1 images) scored on
  each subject's T2 image, another scan with its own noise and bias (the manifest's
  ``evaluation_images``);
* ``multimodal``: the phantom in T1 and T2 (two groups), registered jointly and per group,
  with their affine stages, scored by the mixture specificity;
* ``overfit``: demons with little field smoothing (0.25-5 mm) at the default and at five
  times the iterations;
* ``bspline_grids``: B-spline grids from 2 mm (very fine) to 64 mm;
* ``similar``: the true transforms each perturbed by a smooth random field, two of them of
  the same size (similar true quality) and one twice as large;
* ``folding``: the true transforms perturbed by small local folds (a little folding, a small
  error) against smooth perturbations without folds (larger errors);
* ``families_<...>`` (issue 41): registrations of different families compared in one case,
  each to the cohort's own image 0 (``reference_index: 0``, its transform the identity):
  affine, SimpleITK diffeomorphic demons with field smoothing 0.5, 1, 2 and 4 mm, elastix
  B-splines on 10 and 25 mm grids (:data:`FAMILIES`; ``families_mni2d_syn``: affine, ANTs
  SyN, demons 1 and 3 mm, B-splines on 15 and 40 mm grids, :data:`FAMILIES_SYN`), on
  populations imaged in T1 and T2 with the population's default gain (SD 0.1 of its log),
  smooth multiplicative bias (SD 0.1 of its log) and Rician noise (2% of the template's 99th
  percentile); MNI-based and phantom, N = 12 in 2D (two seeds each), N = 36 and 3D (N = 10,
  3 mm voxels); evaluated inside the reference's brain dilated by 3 voxels, as the demo;
  ``unseen_families_<...>``: the same registrations scored on the T2 images.

**The split** (:data:`TUNING`, :data:`HELD_OUT`, declared before the ``families_*`` cases
were run): a rule may be set on the tuning cases only; ``splits.md`` reports every split in
each mode (:data:`MODES`: with labels, without labels, on the second scan). Fourteen fresh
splits (:data:`FRESH` to :data:`FRESH14`) were each declared before their cases
ran, to check rules changed after the previous split had been seen (``docs/verdict.md``);
:data:`TUNING2`, declared with FRESH14, is a second split a rule may be set on.

Everything a changed verdict needs is saved per case in ``benchmarks/out/verdict/<case>/``
(``evaluation.pkl``: the pickled :class:`~itk_nrreval.EvaluationResult`; ``results.json``;
``truth.json``: the true errors; for the ``families_*`` cases also every subject's true
error in every registration, ``subject_true_error_mm`` and ``subject_true_errors.csv``, for
a subject-QC benchmark), so ``--rejudge`` recomputes only the verdict
(:func:`itk_nrreval.evaluation.verdict`) from them, in seconds. Written to
``benchmarks/out/verdict/``: ``pairs.csv`` / ``pairs.json`` (every pair: case, a, b, true
errors, decision, basis, outcome), ``summary.md`` (per case and overall; also the same
verdict without the overlap, as on data without labels) and ``splits.md`` / ``splits.json``.

Run: ``python benchmarks/run_all.py verdict`` (every case), or
``python benchmarks/bench_verdict.py [--quick] [--new] [--cases a,b] [--missing] [--rejudge]``;
``--quick`` runs ``demo``, ``similar`` and ``folding`` (a few minutes), ``--new`` the
``families_*`` cases and their second scans, ``--splits tuning,tuning2`` the cases of those
splits and their second scans, ``--missing`` only those of them not saved yet
(``benchmarks/out/`` is not in the repository: on a new machine every case, about ten hours
on two cores; a 2D ``families_*`` case takes 2-5 minutes, its second scan under one, a 3D
one 10-15);
whichever cases ran, the tables are written over every saved case.
"""

from __future__ import annotations

import argparse
import csv
import functools
import importlib.util
import io
import itertools
import json
import pickle
import shutil
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import SimpleITK as sitk

HERE = Path(__file__).resolve().parent
OUT = HERE / "out" / "verdict"
N = 12
N_SAMPLES = 20_000
SEED = 0
#: Pairs whose true errors differ by more than this fraction of the smaller are judged.
MARGIN = 0.10
QUICK = ("demo", "similar", "folding")

# ----------------------------------------------------------------- the split (issue 41)
#
# Declared on 2026-11-27, BEFORE the new cases (families_*) were run: it must not be changed
# after seeing their results. A threshold or rule of the verdict may be set (fitted, tuned,
# chosen between alternatives) on TUNING cases only; HELD_OUT cases never set anything and
# are reported in their own column, to tell whether a rule generalizes.
#
# TUNING holds every case that existed before issue 41: the exchange rate 5.5 was set on the
# 2D sweeps (and the 3D MNI sweep), and every other old case was looked at while the three
# generations of rules in docs/verdict.md were written (their wrong decisions motivated the
# changes), so none of them is a case "no one tuned to". It also holds two of the new
# cross-family cases (one MNI-based, one phantom), so a rule about registrations of
# different families can be set at all. HELD_OUT holds the other five new cross-family
# cases: other draws of the same designs (another seed), other families (SyN), N = 36 and
# 3D. Each new case draws its own population seed, so no subject is shared across the split.
# A second scan (unseen_<case>: the same registrations scored on each subject's T2 image) is
# a mode of its case, not a case: it is in its case's split (SECOND_SCAN).
TUNING = (
    "demo",
    "cheat",
    "sweep_phantom2d_fluid",
    "sweep_mni2d_fluid",
    "sweep_phantom2d_pairwise",
    "sweep_mni2d_pairwise",
    "sweep_phantom2d_fluid_update",
    "sweep_phantom2d_bending",
    "sweep_phantom3d_fluid",
    "sweep_mni3d_fluid",
    "multimodal",
    "overfit",
    "bspline_grids",
    "similar",
    "folding",
    "families_mni2d",  # new: MNI-based 2D, N = 12, seed 1: affine, demons x4, B-spline x2
    "families_phantom2d",  # new: phantom 2D, N = 12, seed 1, the same seven registrations
)
HELD_OUT = (
    "families_mni2d_s2",  # MNI-based 2D, N = 12, seed 2, the same seven registrations
    "families_phantom2d_s2",  # phantom 2D, N = 12, seed 2, the same seven
    "families_mni2d_syn",  # MNI-based 2D, N = 12, seed 3: affine, SyN, demons x2, B-spline x2
    "families_mni2d_n36",  # MNI-based 2D, N = 36, seed 4, the seven of families_mni2d
    "families_mni3d",  # MNI-based 3D, N = 10, seed 5, the seven (3D grids)
)
# Declared on 2026-11-27 in the NEXT session, BEFORE these cases were run and before any
# rule of that session was fixed: HELD_OUT had been looked at by then (docs/verdict.md
# reports what a rule fitted on TUNING gives there), so it can no longer be called untouched.
# FRESH cases are judged only after the rules are committed; nothing is set on them.
FRESH = (
    "families_phantom2d_s6",  # phantom 2D, N = 12, seed 6, the seven of families_mni2d
    "families_mni2d_syn_s7",  # MNI-based 2D, N = 12, seed 7, the six of families_mni2d_syn
    "families_mni2d_n24_s8",  # MNI-based 2D, N = 24, seed 8, the seven of families_mni2d
)
# Declared later in the same session, after FRESH had judged the smoother-fields rule and
# before any rule about the overlap was changed, and before these cases were run. FRESH2
# checks what was changed after FRESH was seen.
FRESH2 = (
    "families_mni3d_s10",  # MNI-based 3D, N = 10, seed 10, the seven (3D grids)
    "families_phantom2d_n24_s11",  # phantom 2D, N = 24, seed 11, the seven
    "families_mni2d_syn_s12",  # MNI-based 2D, N = 12, seed 12, the six of families_mni2d_syn
)
# Declared after FRESH2 showed the smoother-fields rule wrong in 3D (B-splines that fold,
# with a lower SDlogJ than demons that correspond better), before the rule was changed for
# it and before these cases were run: two more 3D cases, where the rules are weakest.
FRESH3 = (
    "families_mni3d_s13",  # MNI-based 3D, N = 10, seed 13, the seven (3D grids)
    "families_mni3d_n12_s14",  # MNI-based 3D, N = 12, seed 14, the seven
    "families_mni2d_s15",  # MNI-based 2D, N = 12, seed 15, the seven
)
# Declared after FRESH3 was judged, with the change it checks (a registration "deforms
# locally" by its non-linear displacement, no longer by SDlogJ >= 0.05), before it ran.
FRESH4 = (
    "families_mni3d_s16",  # MNI-based 3D, N = 10, seed 16, the seven (3D grids)
    "families_phantom2d_s17",  # phantom 2D, N = 12, seed 17, the seven
    "families_mni2d_syn_s18",  # MNI-based 2D, N = 12, seed 18, the six of families_mni2d_syn
)
# Declared on 2026-11-28, before these cases were run, with the two rules they check (issue
# 41's held-out case outside the project): specificity is no evidence against a registration
# that folds unless it beats what the preferred one's own roughness could buy, and a
# separable specificity ratio below 1.2 is none where the preferred fields are not clearly
# smoother. Both were taken from that report, not fitted here. Two 3D cases (where B-splines
# fold), N = 36, and two cases of a new mix of families (demons with fluid-like update
# smoothing; B-splines on 20 and 40 mm grids), one of them with N = 16 as in that report.
FRESH5 = (
    "families_mni3d_s19",  # MNI-based 3D, N = 10, seed 19, the seven (3D grids)
    "families_mni3d_n12_s20",  # MNI-based 3D, N = 12, seed 20, the seven
    "families_mni2d_mix_s21",  # MNI-based 2D, N = 12, seed 21, FAMILIES_MIX
    "families_phantom2d_mix_n16_s22",  # phantom 2D, N = 16, seed 22, FAMILIES_MIX
    "families_mni2d_n36_s23",  # MNI-based 2D, N = 36, seed 23, the seven
    "families_mni2d_syn_s24",  # MNI-based 2D, N = 12, seed 24, the six of families_mni2d_syn
)
# Declared on 2026-11-28 after FRESH5 was judged, before these cases ran: FRESH5 found one
# pair wrong with labels (3D: demons at 2 mm over a B-spline on a 10 mm grid that folds
# 1.7% and corresponds better, by the overlap's 1.61x odds), which prompted the same guard
# against a folding registration for the overlap (charged at OVERLAP_EXCHANGE_RATE times
# the preferred registration's own SDlogJ). FRESH6 checks it.
FRESH6 = (
    "families_mni3d_n12_s25",  # MNI-based 3D, N = 12, seed 25, the seven
    "families_mni3d_s26",  # MNI-based 3D, N = 10, seed 26, the seven
    "families_phantom2d_mix_s27",  # phantom 2D, N = 12, seed 27, FAMILIES_MIX
    "families_mni2d_mix_n16_s28",  # MNI-based 2D, N = 16, seed 28, FAMILIES_MIX
)
# Declared on 2026-11-28 after FRESH6 was judged, before these cases ran: FRESH6 found one
# pair wrong in every mode, as under the rules before: in 3D, a 25 mm B-spline folding 4.4%
# preferred by the converse (SMOOTHNESS_RATE) over a 10 mm one folding 8.6% that
# corresponds better. Now a registration that folds (1% or more) is never credited for its
# smoothness. FRESH7 checks it.
FRESH7 = (
    "families_mni3d_s29",  # MNI-based 3D, N = 10, seed 29, the seven
    "families_mni3d_n12_s30",  # MNI-based 3D, N = 12, seed 30, the seven
    "families_phantom2d_n24_s31",  # phantom 2D, N = 24, seed 31, the seven
    "families_mni2d_mix_s32",  # MNI-based 2D, N = 12, seed 32, FAMILIES_MIX
)
# Declared on 2026-11-28 (sixth session of issue 41), BEFORE these cases ran, with no rule
# changed: on every families case so far, every roughness measure followed the true error
# among the deformable registrations and specificity ran against it (docs/verdict.md, "The
# shape model's generalization"): their demons and B-splines all over-fit, so "smoother is
# better" was nearly always right there. FRESH8 spans both sides (FAMILIES_SPAN: demons up
# to 16 mm field smoothing, a B-spline on a 60 mm grid) and checks today's verdict, which
# credits the smoother registration in some pairs, where smoother may be worse.
FRESH8 = (
    "families_mni2d_span_s33",  # MNI-based 2D, N = 12, seed 33, FAMILIES_SPAN
    "families_phantom2d_span_s34",  # phantom 2D, N = 12, seed 34, FAMILIES_SPAN
    "families_mni2d_span_n16_s35",  # MNI-based 2D, N = 16, seed 35, FAMILIES_SPAN
)
# Declared on 2026-11-28 (seventh session of issue 41), BEFORE these cases ran and before any
# description length (issue 41's idea (a), benchmarks/bench_description_length.py) was
# measured on any case: more cases spanning both sides of the best smoothness, where the
# roughness measures lost their hold in FRESH8. FRESH9 checks today's verdict (no rule
# changed) and whatever is set on TUNING for the description length.
FRESH9 = (
    "families_mni2d_span_s36",  # MNI-based 2D, N = 12, seed 36, FAMILIES_SPAN
    "families_phantom2d_span_n16_s37",  # phantom 2D, N = 16, seed 37, FAMILIES_SPAN
    "families_mni2d_span_n24_s38",  # MNI-based 2D, N = 24, seed 38, FAMILIES_SPAN
)
# Declared on 2026-11-28 (seventh session of issue 41), BEFORE these cases ran: the description
# length (benchmarks/bench_description_length.py), measured on every split, decided pairs
# wrong outside TUNING, every one of them between registrations of different families
# (engine and method); FRESH10 checks its preference between settings of one family only,
# a restriction chosen after seeing those splits.
FRESH10 = (
    "families_mni2d_span_s39",  # MNI-based 2D, N = 12, seed 39, FAMILIES_SPAN
    "families_phantom2d_span_s40",  # phantom 2D, N = 12, seed 40, FAMILIES_SPAN
    "families_mni3d_s41",  # MNI-based 3D, N = 10, seed 41, the seven (3D grids)
)
# Declared on 2026-11-28 (sixth session of issue 42), BEFORE these cases ran, with no rule of
# the verdict changed: it checks today's verdict and the description length (issue 41) once
# more, and decides one thing for issue 42. The subject flag on the bias-corrected distance
# (SubjectThresholds.corrected_ratio = 1.4, bench_subject_qc_genuine.py) failed one part of
# its declared check on HELD_OUT's second scans, so it is off by default; it becomes the
# default if, on FRESH11 pooled, in each of the four modes, the recall rises by more than the
# false alarms and at least half of the false alarms it adds are near misses (the same
# check), and stays off otherwise. No later split reopens that decision.
FRESH11 = (
    "families_mni2d_s42",  # MNI-based 2D, N = 12, seed 42, the seven
    "families_phantom2d_n16_s43",  # phantom 2D, N = 16, seed 43, the seven
    "families_mni2d_syn_s44",  # MNI-based 2D, N = 12, seed 44, FAMILIES_SYN
)
# Declared on 2026-11-28 (ninth session of issue 41, seventh of issue 42), BEFORE these cases
# ran, with the two changes they check; nothing is set on them.
# Issue 41: FRESH11 found one pair decided wrong, across families, by the smoother-fields
# rule (SMOOTHNESS_RATE): SyN over demons at 3 mm on the second scan (dr 0.094, the rougher's
# advantage at most 1.12x). That rule now counts only between two registrations of one known
# family (the same method and engine), as the description length does; across families, or
# where a family is unknown, its preference is no evidence and the open pair's reason says
# which way it leans. Chosen after seeing that pair, on the issue's own diagnosis (the rates
# were fitted on sweeps within one engine); measured beforehand on the saved splits: across
# families the rule had fired 299 times without labels where the truth was judged, 298 right
# and this one wrong, so the restriction costs right decisions. Kept if FRESH12 has no pair
# wrong in any mode.
# Issue 42: the subject flag on the bias-corrected distance (corrected_ratio 1.4) failed its
# check only on second scans (HELD_OUT's, FRESH11's), so it is off by default. It becomes the
# default on the images the registrations were made from (off where a manifest scores
# evaluation_images) if, on FRESH12 pooled, on the registered images, with labels and without,
# the recall rises by more percentage points than the false alarms and at least half of the
# false alarms it adds are near misses (true error >= 1.25x the registration's median); it
# stays off otherwise, and no later split reopens it.
FRESH12 = (
    "families_mni2d_syn_s45",  # MNI-based 2D, N = 12, seed 45, FAMILIES_SYN
    "families_phantom2d_syn_s46",  # phantom 2D, N = 12, seed 46, FAMILIES_SYN
    "families_mni2d_mix_n16_s47",  # MNI-based 2D, N = 16, seed 47, FAMILIES_MIX
    "families_mni3d_s48",  # MNI-based 3D, N = 10, seed 48, the seven (3D grids)
)
# Declared on 2026-11-28 (tenth session of issue 41, eighth of issue 42), BEFORE these cases
# ran: it checks today's verdict once more (issue 41), and whatever is set this session on
# TUNING alone before FRESH13 is judged: for issue 41, a lower exchange rate for the
# overlap's preference of a deformable registration over one without local deformation
# (affine), if one is set (the overlap's roughness charge left such pairs open where the
# overlap was right); for issue 42, a per-subject term of the local normalised
# cross-correlation to the others' mean, if one is set. Nothing is set on FRESH13; its
# cases may run before those rules are fixed, but are judged only after they are committed.
FRESH13 = (
    "families_mni2d_s49",  # MNI-based 2D, N = 12, seed 49, the seven
    "families_phantom2d_syn_s50",  # phantom 2D, N = 12, seed 50, FAMILIES_SYN
    "families_mni2d_mix_s51",  # MNI-based 2D, N = 12, seed 51, FAMILIES_MIX
    "families_mni3d_s52",  # MNI-based 3D, N = 10, seed 52, the seven (3D grids)
)
# Declared on 2026-11-29 (eleventh session of issue 41, ninth of issue 42), BEFORE these cases
# ran. TUNING2 is a second tuning split: a rule or threshold may be set on TUNING and TUNING2
# together (TUNING's cross-family cases are two, with 10 failed subjects in all, too few to
# set a subject-QC threshold on). FRESH14 checks whatever is set on them; nothing is set on
# FRESH14, whose cases may run before a rule is fixed but are judged only after it is
# committed.
# Issue 42: a subject flag on the concern (the ranked per-subject score, subject_qc.
# concern_scores): a subject whose concern is above T is flagged. T is the smallest of 1.0,
# 1.25, ..., 4.0 at which the flag itself (whatever other flag the subject carries) flags at
# most 3% of the subjects that did not fail, in each of the four modes (with and without
# labels, registered images and second scans), over TUNING's and TUNING2's families_* cases
# pooled (every registration, affine included). Disclosed: before this declaration, the
# recall and false alarms such a flag would give at thresholds 1-3.5 were printed once for
# TUNING, HELD_OUT, FRESH12 and FRESH13 (no threshold was taken from them; they cannot check
# it). It becomes the default if, on FRESH14 pooled, in each of the four modes, the false
# alarms of all flags together stay at or below the issue's 5% and the recall rises by more
# percentage points than the false alarms; otherwise it stays off (an option), and no later
# split reopens it.
# Set 2026-11-29, before FRESH14 ran: T = 1.75 (bench_subject_qc_genuine.py, the declared
# rule, over TUNING's and TUNING2's families_* cases; its own false alarms there at most 3% in
# every mode, at 1.5 more).
# Issue 41: FRESH14 checks today's verdict once more, and any rule set on TUNING and TUNING2
# before FRESH14 is judged.
TUNING2 = (
    "families_mni2d_s53",  # MNI-based 2D, N = 12, seed 53, the seven
    "families_phantom2d_s54",  # phantom 2D, N = 12, seed 54, the seven
    "families_mni2d_syn_s55",  # MNI-based 2D, N = 12, seed 55, FAMILIES_SYN
    "families_phantom2d_mix_s56",  # phantom 2D, N = 12, seed 56, FAMILIES_MIX
    "families_mni2d_span_s57",  # MNI-based 2D, N = 12, seed 57, FAMILIES_SPAN
    "families_phantom2d_n16_s58",  # phantom 2D, N = 16, seed 58, the seven
)
FRESH14 = (
    "families_mni2d_s59",  # MNI-based 2D, N = 12, seed 59, the seven
    "families_phantom2d_syn_s60",  # phantom 2D, N = 12, seed 60, FAMILIES_SYN
    "families_mni2d_mix_n16_s61",  # MNI-based 2D, N = 16, seed 61, FAMILIES_MIX
    "families_phantom2d_span_s62",  # phantom 2D, N = 12, seed 62, FAMILIES_SPAN
    "families_mni3d_s63",  # MNI-based 3D, N = 10, seed 63, the seven (3D grids)
)
# Declared on 2026-11-29 (twelfth session of issue 41, tenth of issue 42), BEFORE these cases
# ran and before any rule of this session was set. Issue 41: FRESH15 checks any rule set on
# TUNING and TUNING2 in this session, before FRESH15 is judged with it; nothing is set on it.
# Disclosed: before this declaration, which of the overlap's discounted preferences the truth
# agrees with was printed once for every saved case of every split (the overlap's preference
# against a registration that folds agreed with the truth in all 58 such pairs; those for a
# flagged registration in 54 of 139 (first written here as 36 of 105, misread from the same
# print), for a rougher one in 13 of 19), so no split but this one can check a rule about
# them. Issue 42: FRESH15 checks any subject-QC rule set in this session the same way.
FRESH15 = (
    "families_mni2d_s64",  # MNI-based 2D, N = 12, seed 64, the seven
    "families_phantom2d_mix_s65",  # phantom 2D, N = 12, seed 65, FAMILIES_MIX
    "families_mni2d_syn_n16_s66",  # MNI-based 2D, N = 16, seed 66, FAMILIES_SYN
    "families_phantom2d_s67",  # phantom 2D, N = 12, seed 67, the seven
    "families_mni2d_span_s68",  # MNI-based 2D, N = 12, seed 68, FAMILIES_SPAN
    "families_mni3d_s69",  # MNI-based 3D, N = 10, seed 69, the seven (3D grids)
)
# Declared on 2026-11-29 (thirteenth session of issue 41, eleventh of issue 42), BEFORE these
# cases ran and before any rule of this session was set or measured. Issue 41: FRESH16 checks
# any rule set on TUNING and TUNING2 in this session, before FRESH16 is judged with it; nothing
# is set on it. Issue 42: FRESH16 checks any subject-QC rule set in this session the same way,
# in particular a per-subject score that adds to a subject's concern what its concern is under
# the same case's other registrations (a subject that is hard to register is hard for most
# registrations), if one is set: its weight and its flag's threshold are set on TUNING's and
# TUNING2's families_* cases alone, by the rule that set the concern's threshold (the flag's
# own false alarms at most 3% in every mode); it becomes the default if, on FRESH16 pooled, in
# each of the four modes, all flags together keep false alarms at or below the issue's 5% and
# the recall rises by more percentage points than the false alarms; otherwise not.
# Added the same day, while FRESH16 ran and before any of its subject-QC numbers was looked at
# (issue 42): the per-subject score with the concern under the other registrations was measured
# on TUNING and TUNING2 and is not kept (its Spearman with the true error fell as its weight
# rose, 0.83 -> 0.78 with labels at weight 1, and the recall at the rule's threshold rose with
# labels, 48% -> 55%, but fell without, 30% -> 29% and 27% -> 23% on the second scans; first
# written here as "did not rise", corrected from the same print). Instead: a threshold of its
# own for the concern of a cohort without labels (the mean
# of three image and deformation z-scores, which spreads less than the concern with labels,
# half of which is the overlap's z), set by the same rule on the two modes without labels alone
# (the least of 1.0, 1.25, ..., 4.0 at which the flag itself flags at most 3% of the subjects
# that did not fail, in both, over TUNING's and TUNING2's families_* cases); it becomes the
# default if, on FRESH16 pooled, in both modes without labels, all flags together keep false
# alarms at or below 5% and the recall rises by more percentage points than the false alarms.
FRESH16 = (
    "families_mni2d_s70",  # MNI-based 2D, N = 12, seed 70, the seven
    "families_phantom2d_syn_s71",  # phantom 2D, N = 12, seed 71, FAMILIES_SYN
    "families_mni2d_mix_s72",  # MNI-based 2D, N = 12, seed 72, FAMILIES_MIX
    "families_phantom2d_span_n16_s73",  # phantom 2D, N = 16, seed 73, FAMILIES_SPAN
    "families_mni2d_n16_s74",  # MNI-based 2D, N = 16, seed 74, the seven
    "families_mni3d_s75",  # MNI-based 3D, N = 10, seed 75, the seven (3D grids)
)
# Declared on 2026-11-29 (fourteenth session of issue 41, twelfth of issue 42), BEFORE these
# cases ran and before any rule of this session was set or measured. Issue 41: FRESH17 checks
# one rule, to be set on TUNING and TUNING2 alone: between two registrations of different
# families (or of unknown family), a pair today's verdict leaves open but leaning
# (OpenPair.leans_to) becomes a decision for the registration it leans to when the description
# length (evaluate(description_length=True)) prefers the same registration by at least Z
# jackknife standard errors; where it prefers the other, or neither by Z, the pair stays open
# and leaning. Z is the least of 0, 1, 1.96 and 3.2 at which the rule decides no pair wrong on
# TUNING's and TUNING2's cases (registered images and second scans, with and without labels);
# if there is none, nothing is set. It enters the verdict if, on FRESH17, in each of the four
# modes, it decides no pair wrong and decides more pairs right than today's verdict; the older
# splits that set nothing are reported beside FRESH17 but are not its check (their leans were
# printed before this declaration: four pairs lean wrong there, five counting one pair on
# both scans; no description length of theirs was looked at), and a pair it decides wrong
# there also keeps it out. Disclosed: no description
# length has been computed on this machine for any case before this declaration; the first
# measurement, between families, was wrong on seven of eleven splits (docs/verdict.md).
# Added the same day, while FRESH17 ran and before any of its numbers was looked at: the
# tuning cases the rule was measured on are all 2D (TUNING's 3D sweeps are not saved on this
# machine), so, as the verdict does with every rule set on one dimension alone, it is used in
# 2D only; what it would decide in 3D is reported, and is not its check. Set on TUNING and
# TUNING2 by the rule above (before this addition): Z = 0 (none of their 117 leans, counted
# in each of the four modes, is wrong; the description length prefers the lean's registration
# in 108 of them).
# Issue 42: FRESH17 checks any subject-QC rule set in this session on TUNING and TUNING2, as
# FRESH16 did (the concern's rule; all flags at most 5% false alarms in every mode, and the
# recall rising by more points than the false alarms).
FRESH17 = (
    "families_phantom2d_syn_s76",  # phantom 2D, N = 12, seed 76, FAMILIES_SYN
    "families_mni2d_syn_s77",  # MNI-based 2D, N = 12, seed 77, FAMILIES_SYN
    "families_phantom2d_mix_n16_s78",  # phantom 2D, N = 16, seed 78, FAMILIES_MIX
    "families_mni2d_span_s79",  # MNI-based 2D, N = 12, seed 79, FAMILIES_SPAN
    "families_phantom2d_s80",  # phantom 2D, N = 12, seed 80, the seven
    "families_mni3d_s81",  # MNI-based 3D, N = 10, seed 81, the seven (3D grids)
)
# Declared on 2026-11-29 (fourteenth session of issue 41), BEFORE these cases ran, after
# FRESH17 was judged: FRESH17 had the smoother-fields rule decide, within one family, a 60 mm
# B-spline grid over a 25 mm one that corresponded better (1.86 against 1.34 mm), which the
# description length preferred at z = 2.3, below its MIN_Z (3.2). FRESH18 checks one rule,
# set on TUNING and TUNING2 alone before it was declared: within one family, the smoother-
# fields rule's evidence is no evidence where the description length prefers the rougher
# registration by more than 1.1 jackknife standard errors (the steepest right smoother-fields
# decision the description length disagreed with there was at 0.99, on sweep_mni2d_pairwise:
# a 64 mm grid over an 8 mm one; plus 10%). It enters the verdict if, on FRESH18 (registered
# images and second scans, with and without labels, each case with its description length),
# it opens no pair decided right and no pair is decided wrong; the older splits that set
# nothing are reported beside it. All 2D: the rule is used in 2D only, as it was set there.
FRESH18 = (
    "families_mni2d_span_s82",  # MNI-based 2D, N = 12, seed 82, FAMILIES_SPAN
    "families_phantom2d_span_s83",  # phantom 2D, N = 12, seed 83, FAMILIES_SPAN
    "families_mni2d_span_n16_s84",  # MNI-based 2D, N = 16, seed 84, FAMILIES_SPAN
    "families_mni2d_s85",  # MNI-based 2D, N = 12, seed 85, the seven
    "families_phantom2d_syn_s86",  # phantom 2D, N = 12, seed 86, FAMILIES_SYN
)
# Declared on 2026-11-29 (fifteenth session of issue 41), BEFORE these cases ran. FRESH17
# had two pairs decided wrong, by two numbers set on the tuning splits. Two changes, each of
# which only leaves pairs open, set on every split judged so far (FRESH17 and the older
# splits now set these two numbers; FRESH19 checks them):
# (1) SMOOTHNESS_RATE 2.3 -> 1.95: on families_mni2d_span_s79 the 25 mm grid, rougher than
#     the 60 mm one and corresponding better, had its advantage at the top of its interval at
#     exp(2.21 dr) (2.18 on the second scan), below 2.3; 1.95 is 10% below the shallowest
#     such pair on any split judged (2.18).
# (2) Between registrations of different (or unknown) families, specificity's preference for
#     the rougher one, against one that deforms locally, is evidence only where ln(ratio) /
#     dr reaches EXCHANGE_RATE_ACROSS_FAMILIES = 6.6 (5.5 within one family):
#     families_phantom2d_syn_s76 had demons at 3 mm decided over a 40 mm grid that
#     corresponded better at 5.98; 6.6 is 10% above it.
# FRESH19 checks them: neither rule decides a pair wrong in any mode (registered images and
# second scans, with and without labels); what they leave open that the rules before decided
# right is reported beside the older splits' count. All 2D (both FRESH17 pairs were 2D; the
# 3D cases take too long for one session). Issue 42: no subject-QC rule changed; FRESH19
# reports today's flags.
FRESH19 = (
    "families_phantom2d_syn_s87",  # phantom 2D, N = 12, seed 87, FAMILIES_SYN
    "families_mni2d_span_s88",  # MNI-based 2D, N = 12, seed 88, FAMILIES_SPAN
    "families_phantom2d_span_n16_s89",  # phantom 2D, N = 16, seed 89, FAMILIES_SPAN
    "families_mni2d_syn_s90",  # MNI-based 2D, N = 12, seed 90, FAMILIES_SYN
    "families_phantom2d_mix_s91",  # phantom 2D, N = 12, seed 91, FAMILIES_MIX
    "families_mni2d_span_n16_s92",  # MNI-based 2D, N = 16, seed 92, FAMILIES_SPAN
)
# Declared on 2026-11-29 (sixteenth session of issue 41), BEFORE these cases ran. Two of the
# verdict's leans become decisions (without labels they were 29% of the judged pairs over
# the splits above, right in all but 5 of about 1,000), set on every split judged so far
# (all of them now set these numbers; FRESH20 checks them):
# (1) The smoother-fields rule between registrations of different (or unknown) families
#     decides where the rougher one's SDlogJ is higher by at least
#     ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE = 0.2; below it, it still leans. The four wrong
#     leans of this kind were at 0.09 (FRESH11, FRESH19: SyN over demons at 3 mm) and 0.17
#     (FRESH13, both scans: demons at 3 mm over a 15 mm grid); 0.2 is 10% above 0.17, rounded up.
# (2) In 2D, specificity's preference for a registration that deforms locally over one that
#     does not (affine) decides where ln(ratio) / SDlogJ reaches
#     SPECIFICITY_DECIDES_AGAINST_LINEAR = 2.5 (it leans from 1.75); the one wrong lean of this
#     kind was at 2.2 (FRESH6: demons at 2 mm over affine); 2.5 is 10% above it, rounded up.
# FRESH20 checks them: kept only if no pair is decided wrong in any mode (registered images
# and second scans, with and without labels); the older splits are reported beside it. All 2D
# (rule 2 is 2D only; the 3D cases take too long for one session). Issue 42: no subject-QC
# rule changed; FRESH20 reports today's flags.
FRESH20 = (
    "families_mni2d_mix_s93",  # MNI-based 2D, N = 12, seed 93, FAMILIES_MIX
    "families_phantom2d_s94",  # phantom 2D, N = 12, seed 94, the seven
    "families_mni2d_syn_n16_s95",  # MNI-based 2D, N = 16, seed 95, FAMILIES_SYN
    "families_phantom2d_span_s96",  # phantom 2D, N = 12, seed 96, FAMILIES_SPAN
    "families_mni2d_s97",  # MNI-based 2D, N = 12, seed 97, the seven
    "families_phantom2d_syn_s98",  # phantom 2D, N = 12, seed 98, FAMILIES_SYN
)
# Declared on 2026-11-29 (sixteenth session of issue 41), after FRESH20 was judged and BEFORE
# these cases ran. One rule more, the converse of specificity against affine, set on every
# split judged so far (FRESH20 included; FRESH21 checks it): in 2D, a registration that
# deforms locally and folds less than 1% is decided WORSE than an affine one where its
# specificity advantage over affine, at the top of its subject-level interval, is below
# exp(SMOOTHNESS_RATE_AGAINST_LINEAR s), s its SDlogJ, SMOOTHNESS_RATE_AGAINST_LINEAR = 1.25.
# Over those pairs (2D, not folding) the lowest such advantage where the deformable one
# corresponded better was exp(1.42 s) (FRESH11, families_mni2d_s42's second scan: a 25 mm
# grid); 1.25 is 10% below it, rounded down. FRESH21 checks it: kept only if it decides no
# pair wrong in any mode (registered images and second scans, with and without labels);
# what the verdict's older rules decide wrong there is reported apart. All 2D (the rule is
# 2D only). Issue 42: no subject-QC rule changed; FRESH21 reports today's flags.
FRESH21 = (
    "families_mni2d_span_s99",  # MNI-based 2D, N = 12, seed 99, FAMILIES_SPAN
    "families_phantom2d_mix_s100",  # phantom 2D, N = 12, seed 100, FAMILIES_MIX
    "families_mni2d_n16_s101",  # MNI-based 2D, N = 16, seed 101, the seven
    "families_phantom2d_span_n16_s102",  # phantom 2D, N = 16, seed 102, FAMILIES_SPAN
    "families_mni2d_syn_s103",  # MNI-based 2D, N = 12, seed 103, FAMILIES_SYN
    "families_phantom2d_s104",  # phantom 2D, N = 12, seed 104, the seven
)
# Declared on 2026-11-29 (seventeenth session of issue 41), BEFORE these cases ran, after
# FRESH21 was judged. A preference over a registration that folds (at least 1%, and more than
# the preferred one) is charged as if the folding one's fields were flat: its gain must reach
# what the preferred registration's own SDlogJ s could buy. At EXCHANGE_RATE (specificity) and
# OVERLAP_EXCHANGE_RATE (the overlap, 3D only) that charge left 209 such specificity
# preferences open or decided by other evidence where the truth agreed with them, and 2 where
# it did not; for the overlap, 75 and 2. The 2 are one pair, both scans (FRESH5,
# families_mni3d_n12_s20: demons at 2 mm over a 10 mm B-spline folding 1.7%, 3.88 vs 3.51
# mm), at ln(ratio) / s = 0.37 (specificity, second scan) and 1.02 (the overlap). So the
# charge is now at its own rates, 10% beyond that pair, rounded away from it:
#     SPECIFICITY_RATE_AGAINST_FOLDS = 0.41, OVERLAP_RATE_AGAINST_FOLDS = 1.13
# (the overlap's still only outside OVERLAP_AGAINST_FOLDS_DIMENSIONS: in 2D it is not
# charged). Set on every split judged so far (TUNING to FRESH21, held-out excepted).
# Amended within the hour, before any FRESH22 case had finished or been looked at: the lower
# rates apply only where the folding registration folds at least CLEARLY_FOLDS_FRACTION =
# 2.5% (below, the exchange rates stay). Issue 41's own outside case had demons at 1 mm
# (SDlogJ 0.29) decided by specificity over a 25 mm B-spline folding 2.3% that corresponded
# better; its ratio is not in the report, and 0.41 would ask only 1.13x of it. 2.5% is 10%
# beyond 2.3%, rounded away (FRESH5's pair folds 1.7%). On the judged splits it costs 11 of
# the 140 specificity preferences the rate would free. FRESH22 checks both: kept only if
# they decide no pair wrong in any mode (registered images and second scans, with and
# without labels). Two 3D cases (the overlap's rate is 3D only) and four 2D cases with a
# 10 mm B-spline that folds.
# Issue 42, amended the same way (one FRESH22 case had finished running, but no subject-QC number
# of FRESH22 was computed or looked at): the flag on the concern without labels, SubjectThresholds.
# concern_without_labels, is set by its own declared rule (the least of 1.0, 1.25, ..., 4.0
# at which the flag itself flags at most 3% of the subjects that did not fail, in both modes
# without labels) on every split judged so far but held-out (TUNING..FRESH21), no longer on
# TUNING and TUNING2 alone: 1.25 (1.75 before). FRESH22 decides, by FRESH16's criterion: it
# becomes the default if on FRESH22 pooled, in both modes without labels, all flags together
# keep the false alarms at or below 5% and the recall rises by more points than the false
# alarms. The threshold with labels, by the same rule on the same splits, stays 1.75.
FRESH22 = (
    "families_mni3d_s105",  # MNI-based 3D, N = 10, seed 105, the seven (3D grids)
    "families_mni2d_s106",  # MNI-based 2D, N = 12, seed 106, the seven
    "families_mni3d_n12_s107",  # MNI-based 3D, N = 12, seed 107, the seven (3D grids)
    "families_mni2d_span_n16_s108",  # MNI-based 2D, N = 16, seed 108, FAMILIES_SPAN
    "families_phantom2d_s109",  # phantom 2D, N = 12, seed 109, the seven
    "families_mni2d_n16_s110",  # MNI-based 2D, N = 16, seed 110, the seven
)
# Declared on 2026-11-29 (eighteenth session of issue 41), BEFORE these cases ran; nothing is
# set on them and no rule changed with them. The charge against a registration that folds
# (CLEARLY_FOLDS_FRACTION, SPECIFICITY_RATE_AGAINST_FOLDS, OVERLAP_RATE_AGAINST_FOLDS, and the
# exchange rates between 1% and 2.5%) was set where nearly every registration that folds is a
# 10 or 25 mm B-spline. FRESH23 meets it with one that folds for another reason:
# diffeomorphic demons with 0.1 mm field smoothing (too little to regularise; on five images
# of TUNING's families_mni2d population, not these, 2.2-3.4% of the voxels folded), beside
# the 10 mm B-spline that folds and five that do not (FAMILIES_FOLD). The check: no pair
# decided wrong in any mode (registered images and second scans, with and without labels);
# reported per case with the leans. Subject QC (issue 42) is reported on it too, as it is.
FRESH23 = (
    "families_mni2d_fold_s111",  # MNI-based 2D, N = 12, seed 111, FAMILIES_FOLD
    "families_phantom2d_fold_s112",  # phantom 2D, N = 12, seed 112, FAMILIES_FOLD
    "families_mni2d_fold_n16_s113",  # MNI-based 2D, N = 16, seed 113, FAMILIES_FOLD
    "families_phantom2d_fold_s114",  # phantom 2D, N = 12, seed 114, FAMILIES_FOLD
)
# Declared on 2026-11-29 (eighteenth session of issue 41), BEFORE these cases ran, after
# FRESH23 was judged and found one pair decided wrong (both modes of a second scan): a 10 mm
# B-spline folding 10.9% over demons folding 3.4%, by specificity. The rule committed for
# it (45ab448): specificity's preference for a registration that clearly folds
# (CLEARLY_FOLDS_FRACTION, 2.5%) and more than the other is no evidence. 2.5% rather than 1%
# was chosen on TUNING (from 1% it opens 2 right pairs there; at 2.5% nothing changes on
# TUNING, TUNING2 or held-out). FRESH23 set it; FRESH24, FAMILIES_FOLD on new seeds, checks
# it: no pair decided wrong in any mode, and what it costs (right pairs it opens).
FRESH24 = (
    "families_mni2d_fold_s115",  # MNI-based 2D, N = 12, seed 115, FAMILIES_FOLD
    "families_phantom2d_fold_s116",  # phantom 2D, N = 12, seed 116, FAMILIES_FOLD
    "families_mni2d_fold_s117",  # MNI-based 2D, N = 12, seed 117, FAMILIES_FOLD
    "families_phantom2d_fold_n16_s118",  # phantom 2D, N = 16, seed 118, FAMILIES_FOLD
)
# Declared on 2026-11-28 (fourth session of issue 41), BEFORE any case outside TUNING was
# judged with it: a new label-free measure, specificity at a common smoothness (every
# registration's fields smoothed by a Gaussian of 8 mm before resampling), and its rule, set
# on TUNING alone: its preference (at least 1.2x) is evidence where neither registration
# folds 1% of its voxels, the preferred one deforms locally, and either the other deforms
# locally and the preferred is not rougher by 0.05 in SDlogJ, or the other is affine and the
# ratio reaches exp(0.8 SDlogJ(preferred)). 8 mm and 4 mm gave the same decisions on TUNING;
# 0.8 is the middle (geometric) of the rates that separate TUNING's deformable-versus-affine
# pairs (0.46 to 1.33). HELD_OUT and FRESH..FRESH7 check it: nothing is set on them.
# Declared later the same day, after HELD_OUT and FRESH (and FRESH2's families_mni3d_s10,
# judged with them, no pair wrong) showed that rule wrong in 3D: a 25 mm B-spline folding
# 0.71% (SDlogJ 0.35) had a 1.75x lower specificity at a common smoothness than the affine
# registration, which corresponded better (4.41 vs 3.37 mm), on the registered images and
# on the second scan. No exchange rate that TUNING allows separates that pair, so the
# measure's evidence against an affine registration is dropped: it now counts only between
# two registrations that deform locally (the other branch, unchanged). Set before the rest
# of FRESH2 and FRESH3..FRESH7 were judged with specificity at a common smoothness; they
# check it.
#: Each split's cases, in the order the splits were declared.
SPLIT_CASES = {
    "tuning": TUNING, "held-out": HELD_OUT, "fresh": FRESH, "fresh2": FRESH2, "fresh3": FRESH3,
    "fresh4": FRESH4, "fresh5": FRESH5, "fresh6": FRESH6, "fresh7": FRESH7, "fresh8": FRESH8,
    "fresh9": FRESH9, "fresh10": FRESH10, "fresh11": FRESH11, "fresh12": FRESH12,
    "fresh13": FRESH13, "tuning2": TUNING2, "fresh14": FRESH14, "fresh15": FRESH15,
    "fresh16": FRESH16, "fresh17": FRESH17, "fresh18": FRESH18, "fresh19": FRESH19,
    "fresh20": FRESH20, "fresh21": FRESH21, "fresh22": FRESH22, "fresh23": FRESH23,
    "fresh24": FRESH24,
}  # fmt: skip
SPLITS = tuple(SPLIT_CASES)
#: Every case of a declared split.
DECLARED = tuple(case for cases in SPLIT_CASES.values() for case in cases)
#: A case -> the case of the same registrations scored on a second scan (the T2 images).
SECOND_SCAN = {
    **{
        f"sweep_{c}": f"unseen_{c}"
        for c in (
            "phantom2d_fluid",
            "mni2d_fluid",
            "phantom2d_pairwise",
            "mni2d_pairwise",
            "phantom2d_bending",
        )
    },
    **{c: f"unseen_{c}" for c in DECLARED if c.startswith("families_")},
}
#: Package modules moved into rooms by issue 43 (io/, measures/, experiments/), by room.
_ROOMS = {
    "io": (
        "_affine_fit _brain_masks _cache _displacements _elastix_files _field_kernels "
        "_field_orientation _foreign_transforms _grid_slabs _images _in_memory_images _itk_hdf5 "
        "_jacobian_kernels _label_channels _manifest_entries _manifest_files _membership_files "
        "_membership_kernels _memberships _plausibility_thresholds _resampled_images "
        "_transform_inversion _transform_io _transform_patterns frame label_names manifest "
        "plausibility transforms"
    ),
    "measures": (
        "_overlap_kernels _overlap_sums _ranks _reference_subject _subject_flags "
        "_subject_measures _transform_mixups confidence label_metrics model overlap specificity "
        "subject_qc verdict"
    ),
    "experiments": (
        "_clamped_plate_spline _fold_check _perturbed_sets correspondence demo sweep warps"
    ),
}
#: ... and those it renamed on the way: old name -> new dotted name under itk_nrreval.
_RENAMED_INTO_ROOMS = {
    "derivatives": "io.pipeline_outputs",
    "validation": "experiments.perturbation",
    "_validation_inputs": "experiments._perturbation_inputs",
    "appearance": "experiments.appearance.model",
    "diagnostics": "experiments.appearance.diagnose",
}
_ISSUE_43 = {
    **{
        f"itk_nrreval.{name}": f"itk_nrreval.{room}.{name}"
        for room, names in _ROOMS.items()
        for name in names.split()
    },
    **{f"itk_nrreval.{old}": f"itk_nrreval.{new}" for old, new in _RENAMED_INTO_ROOMS.items()},
}
#: Issue 28 underscored the implementation modules (Coverage, in every EvaluationResult,
#: lived in the pipeline one).
_ISSUE_28 = {
    f"itk_nrreval.{name}": f"itk_nrreval._{name}"
    for name in ("cache", "pipeline", "scaleout", "memberships", "elastix_files")
}
#: Package modules renamed since evaluations were saved: old name -> today's name, so that a
#: saved evaluation.pkl still loads. Subpackages moved whole are in :data:`MOVED_PACKAGES`.
RENAMED_MODULES = {
    **_ISSUE_43,
    **{old: _ISSUE_43.get(new, new) for old, new in _ISSUE_28.items()},
}
#: Subpackages issue 43 moved into rooms, every module in them with them.
MOVED_PACKAGES = {
    "itk_nrreval.registration": "itk_nrreval.experiments.registration",
    "itk_nrreval._search": "itk_nrreval.measures._search",
}


def _renamed(module: str) -> str:
    """Where the classes of a module that a saved evaluation names live today."""
    if module in RENAMED_MODULES:
        return RENAMED_MODULES[module]
    for old, new in MOVED_PACKAGES.items():
        if module == old or module.startswith(old + "."):
            return new + module[len(old) :]
    return module


class _RenamingUnpickler(pickle.Unpickler):
    """An unpickler that finds a class of a renamed module (:data:`RENAMED_MODULES`,
    :data:`MOVED_PACKAGES`) under its new module name."""

    def find_class(self, module: str, name: str):
        return super().find_class(_renamed(module), name)


@functools.cache
def _bench(name: str):
    """Another benchmark module of this folder (its builders are reused, not copied); loaded
    once (:func:`_load` asks for one for every saved case)."""
    path = HERE / f"bench_{name}.py"
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _quiet(function, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # flags and coverage are what is measured here
        return function(*args, **kwargs)


def _true_errors(evaluation, manifest: Path, data_manifest: Path) -> dict[str, float]:
    """True correspondence error (mm) of every registration, inside the manifest's mask."""
    from itk_nrreval.experiments.sweep import _truth_error
    from itk_nrreval.io.manifest import load_manifest
    from itk_nrreval.io.transforms import chain_transform

    truth = load_manifest(data_manifest).registrations["truth"]
    chains = [chain_transform(t) for t in truth.transforms]
    return _truth_error(evaluation, manifest, chains, truth.reference)


# ------------------------------------------------------------------------------------ cases


def _demo(folder: Path):
    from itk_nrreval.experiments.demo import run_demo

    demo = _quiet(
        run_demo, out=folder, n=N, n_samples=N_SAMPLES, seed=SEED, progress=False, log=print
    )
    return demo.evaluation, demo.correspondence_error_mm


def _cheat(folder: Path):
    import itk_nrreval as nr

    demo = OUT / "demo"
    if not (demo / "manifest.yaml").exists():
        _run_case("demo")
    manifest = _bench("cheat").add_cheat(demo)  # beside the demo's registrations
    ev = _quiet(nr.evaluate, manifest, n_samples=N_SAMPLES, seed=SEED, progress=False)
    return ev, _true_errors(ev, manifest, demo / "data" / "manifest.yaml")


def _sweep(
    folder: Path, *, kind: str, method: str, parameters: dict, engine=None, dim=2, n=N, spacing=None
):
    from itk_nrreval.experiments.sweep import sweep
    from itk_nrreval.io.manifest import load_manifest
    from itk_nrreval.io.transforms import chain_transform

    data = _population(kind, dim=dim, n=n, spacing=spacing)
    m = load_manifest(data)
    truth = m.registrations["truth"]
    res = _quiet(
        sweep,
        list(m.images),
        method=method,
        parameters=parameters,
        out=folder / "sweep",
        labels=list(m.labels),
        engine=engine,
        truth=[chain_transform(t) for t in truth.transforms],
        truth_reference=truth.reference,
        n_samples=N_SAMPLES,
        seed=SEED,
        progress=False,
    )
    return res.evaluation, dict(res.truth_error_mm)


def _unseen(folder: Path, *, sweep_case: str, kind: str):
    """The registrations of `sweep_case` (made on the T1 images), scored on each subject's
    T2 image: another scan with its own noise and bias, which the registration did not see
    (the manifest's ``evaluation_images``). Same seed, so the T1 images are the sweep's."""
    swept = OUT / sweep_case / "sweep" / "manifest.yaml"
    if not swept.exists():
        _run_case(sweep_case)
    data = _population(kind, contrasts=("t1", "t2"))
    return _second_scan(folder, case=sweep_case, registered=swept, data=data)


def _second_scan(folder: Path, *, case: str, registered: Path, data: Path):
    """The registrations of the manifest `registered` (of case `case`, made on the T1 images
    of the population `data`), scored on each subject's T2 image of `data` (the manifest's
    ``evaluation_images``); the true errors are `case`'s."""
    import dataclasses

    import itk_nrreval as nr
    from itk_nrreval.io.manifest import load_manifest, write_manifest

    both = load_manifest(data)
    t1 = [p for p, g in zip(both.images, both.groups, strict=True) if g == "t1"]
    t2 = [p for p, g in zip(both.images, both.groups, strict=True) if g == "t2"]
    m = load_manifest(registered)
    for a, b in zip(m.images, t1, strict=True):  # the registered images are these T1 images
        same = sitk.GetArrayFromImage(sitk.ReadImage(str(a))) == sitk.GetArrayFromImage(
            sitk.ReadImage(str(b))
        )
        assert same.all(), (a, b)
    manifest = write_manifest(
        dataclasses.replace(m, evaluation_images=tuple(t2)), folder / "manifest.yaml"
    )
    ev = _quiet(nr.evaluate, manifest, n_samples=N_SAMPLES, seed=SEED, progress=False)
    truth = json.loads((OUT / case / "truth.json").read_text())
    return ev, truth["true_error_mm"], {k: v for k, v in truth.items() if k.startswith("subject")}


def _multimodal(folder: Path):
    """The phantom imaged in T1 and T2 (one group each), registered by
    :func:`itk_nrreval.experiments.registration.register_multimodal` (joint, per-group, and their
    affine stages) and scored with the mixture specificity (:mod:`bench_multimodal`'s runs)."""
    import itk_nrreval as nr
    from data_synth import make_population, write_population
    from itk_nrreval.experiments.correspondence import correspondence_error
    from itk_nrreval.experiments.registration import ElastixWorker, register_multimodal
    from itk_nrreval.io.manifest import load_manifest

    runs = _bench("multimodal").RUNS
    contrasts = ("t1", "t2")
    pop = make_population("phantom", dim=2, n=N, seed=SEED, contrasts=contrasts)
    manifest = write_population(pop, folder / "data", montage=False, progress=False)
    m = load_manifest(manifest)
    images = [str(p) for p in m.images]
    names = [Path(p).name.removesuffix(".nii.gz") for p in images]
    with ElastixWorker() as worker:
        for name, kwargs in runs.items():
            result = _quiet(
                register_multimodal,
                images,
                m.groups,
                **kwargs,
                seed=SEED,
                progress=False,
                elastix_worker=worker,
            )
            result.add_to_manifest(manifest, name, out=folder / name, names=names)
    ev = _quiet(nr.evaluate, manifest, n_samples=N_SAMPLES, seed=SEED, progress=False)
    head = sitk.GetArrayFromImage(pop.template_labels) > 0
    truth = [s.subject_to_template for _ in contrasts for s in pop.subjects]
    return ev, correspondence_error(ev, manifest, truth, mask=head)


def _population(
    kind: str,
    *,
    dim: int = 2,
    n: int = N,
    spacing: float | None = None,
    seed: int = SEED,
    contrasts: tuple[str, ...] = ("t1",),
) -> Path:
    """The manifest of a generated population (written once, then read from its folder);
    the population's default noise, bias and gain (:func:`data_synth.make_population`)."""
    from data_synth import make_population, write_population

    grid = "" if spacing is None else f"_{spacing:g}mm"
    drawn = "" if seed == SEED else f"_seed{seed}"
    scans = "" if contrasts == ("t1",) else "_" + "".join(contrasts)
    manifest = OUT / f"data_{kind}{dim}d_n{n}{grid}{drawn}{scans}" / "manifest.yaml"
    if not manifest.exists():
        extra = {} if spacing is None else {"spacing": spacing}
        pop = make_population(kind, dim=dim, n=n, seed=seed, contrasts=contrasts, **extra)
        write_population(pop, manifest.parent, montage=False, progress=False)
    return manifest


def _perturbed(folder: Path, perturbations: dict[str, list[np.ndarray]]):
    """The true transforms, each perturbed first by a displacement field on the template grid.

    `perturbations` maps a registration name to one field per subject (numpy order, mm,
    components x, y): registration ``name`` maps p to ``truth_i(p + u_i(p))``.
    """
    import itk_nrreval as nr
    from data_synth.population import _field_image
    from itk_nrreval.io.manifest import add_registration, load_manifest

    data = _population("phantom")
    truth = load_manifest(data).registrations["truth"]
    template = sitk.ReadImage(str(truth.reference))
    manifest = folder / "manifest.yaml"
    manifest.unlink(missing_ok=True)
    m = load_manifest(data)
    for name, fields in perturbations.items():
        items = []
        for i, (u, chain) in enumerate(zip(fields, truth.transforms, strict=True)):
            path = folder / name / f"s{i:02d}.mha"
            path.parent.mkdir(parents=True, exist_ok=True)
            sitk.WriteImage(_field_image(u, template), str(path))
            chain = chain if isinstance(chain, (list, tuple)) else [chain]
            items.append([str(path), *[str(p) for p in chain]])
        add_registration(
            manifest,
            name,
            reference=truth.reference,
            transforms=items,
            images=list(m.images),
            labels=list(m.labels),
        )
    ev = _quiet(nr.evaluate, manifest, n_samples=N_SAMPLES, seed=SEED, progress=False)
    return ev, _true_errors(ev, manifest, data)


def _smooth_fields(seed: int, rms_mm: float, sigma_mm: float = 12.0) -> list[np.ndarray]:
    """One smooth random displacement per subject, RMS `rms_mm`, vanishing at the border."""
    from data_synth.population import _smooth_noise, _taper

    template = sitk.ReadImage(str(_truth_reference()))
    rng = np.random.default_rng(seed)
    taper = _taper(template)[..., None]
    return [
        rms_mm * taper * _smooth_noise(rng, template, n_components=2, sigma_mm=sigma_mm)
        for _ in range(N)
    ]


def _fold_fields(seed: int, *, n_bumps: int = 8, sigma_mm: float = 4.0, amplitude_mm: float = 12.0):
    """Per subject, `n_bumps` small radial bumps inside the head: each folds in a thin ring.

    The bump ``A (r / s) exp(-r^2 / 2 s^2)`` folds where its radial derivative is below -1,
    a ring around ``r = sqrt(3) s`` once ``A > 2.24 s``; it is zero a few ``s`` away.
    """
    template = sitk.ReadImage(str(_truth_reference()))
    arr = sitk.GetArrayFromImage(template)
    inside = np.argwhere(arr > 0.3 * arr.max())  # numpy (y, x) indices inside the head
    spacing = np.asarray(template.GetSpacing())[::-1]  # numpy order
    yy, xx = np.indices(arr.shape)
    rng = np.random.default_rng(seed)
    fields = []
    for _ in range(N):
        u = np.zeros((*arr.shape, 2))
        for cy, cx in inside[rng.choice(len(inside), n_bumps, replace=False)]:
            dy, dx = (yy - cy) * spacing[0], (xx - cx) * spacing[1]
            bump = amplitude_mm / sigma_mm * np.exp(-(dx**2 + dy**2) / (2 * sigma_mm**2))
            u[..., 0] += bump * dx  # ITK component order: x, y
            u[..., 1] += bump * dy
        fields.append(u)
    return fields


def _truth_reference() -> Path:
    from itk_nrreval.io.manifest import load_manifest

    return Path(load_manifest(_population("phantom")).registrations["truth"].reference)


#: The registrations of a cross-family case, all to the cohort's own image 0 (its transform
#: the identity): name -> (method, engine, options of
#: :func:`itk_nrreval.experiments.registration.register`). The seven of the issue's held-out case:
#: affine, diffeomorphic demons (SimpleITK) with field smoothing of 0.5-4 mm, B-spline (elastix) on
#: a fine and a coarse grid.
FAMILIES = {
    "affine": ("affine", "simpleitk", {}),
    **{f"demons_{s:g}mm": ("fluid", "simpleitk", {"smoothing_mm": s}) for s in (0.5, 1, 2, 4)},
    **{f"bspline_{g:g}mm": ("pairwise", "elastix", {"grid_spacing": g}) for g in (10.0, 25.0)},
}
#: Other families and settings: ANTs SyN, demons at 1 and 3 mm, B-spline on 15 and 40 mm grids.
FAMILIES_SYN = {
    "affine": FAMILIES["affine"],
    "syn": ("fluid", "ants", {}),
    **{f"demons_{s:g}mm": ("fluid", "simpleitk", {"smoothing_mm": s}) for s in (1, 3)},
    **{f"bspline_{g:g}mm": ("pairwise", "elastix", {"grid_spacing": g}) for g in (15.0, 40.0)},
}

#: A third mix (FRESH5): SyN, demons with field smoothing and demons with fluid-like update
#: smoothing, B-splines on 20 and 40 mm grids.
FAMILIES_MIX = {
    "affine": FAMILIES["affine"],
    "syn": FAMILIES_SYN["syn"],
    "demons_2mm": ("fluid", "simpleitk", {"smoothing_mm": 2.0}),
    "demons_update_2mm": ("fluid", "simpleitk", {"smoothing_mm": 1.0, "update_smoothing_mm": 2.0}),
    **{f"bspline_{g:g}mm": ("pairwise", "elastix", {"grid_spacing": g}) for g in (20.0, 40.0)},
}


#: Both sides of the smoothness that corresponds best (FRESH8): demons from rough (1 mm) to
#: over-smooth (16 mm field smoothing), B-splines from a fine (10 mm) to a coarse (60 mm) grid.
FAMILIES_SPAN = {
    "affine": FAMILIES["affine"],
    **{f"demons_{s:g}mm": ("fluid", "simpleitk", {"smoothing_mm": s}) for s in (1, 4, 8, 16)},
    **{
        f"bspline_{g:g}mm": ("pairwise", "elastix", {"grid_spacing": g}) for g in (10.0, 25.0, 60.0)
    },
}


#: A registration that folds for another reason than a coarse grid (FRESH23): diffeomorphic
#: demons with 0.1 mm field smoothing, beside demons at 0.5, 2 and 4 mm, and B-splines on a
#: 10 mm grid (which folds) and a 25 mm one.
FAMILIES_FOLD = {
    "affine": FAMILIES["affine"],
    **{f"demons_{s:g}mm": ("fluid", "simpleitk", {"smoothing_mm": s}) for s in (0.1, 0.5, 2, 4)},
    **{f"bspline_{g:g}mm": ("pairwise", "elastix", {"grid_spacing": g}) for g in (10.0, 25.0)},
}


def _families(
    folder: Path,
    *,
    kind: str,
    seed: int,
    registrations: dict = FAMILIES,
    dim: int = 2,
    n: int = N,
    spacing: float | None = None,
):
    """Registrations of different families, each to the cohort's own image 0
    (``reference_index: 0``), of a population imaged in T1 and T2 (the population's default
    gain, bias and Rician noise); registered on the T1 images, evaluated like the demo inside
    the reference's brain dilated by 3 voxels. The T2 images are the case's second scan
    (``unseen_<case>``, :func:`_second_scan`)."""
    import dataclasses

    import itk_nrreval as nr
    from itk_nrreval.experiments.registration import ElastixWorker, register
    from itk_nrreval.io.manifest import load_manifest, write_manifest

    data = _population(kind, dim=dim, n=n, spacing=spacing, seed=seed, contrasts=("t1", "t2"))
    both = load_manifest(data)
    t1 = [i for i, g in enumerate(both.groups) if g == "t1"]
    images = [str(both.images[i]) for i in t1]
    labels = [str(both.labels[i]) for i in t1]
    names = [Path(p).name.removesuffix(".nii.gz") for p in images]
    manifest = folder / "manifest.yaml"
    seconds = {}
    t0 = time.perf_counter()
    affine = _quiet(register, images, method="affine", reference=0, seed=SEED, progress=False)
    seconds["affine"] = time.perf_counter() - t0
    with ElastixWorker() as worker:
        for name, (method, engine, options) in registrations.items():
            t0 = time.perf_counter()
            if method == "affine":
                result = affine
            else:
                result = _quiet(
                    register,
                    images,
                    method=method,
                    engine=engine,
                    options=options,
                    affine=affine,
                    seed=SEED,
                    progress=False,
                    elastix_worker=worker if method == "pairwise" else None,
                )
                seconds[name] = time.perf_counter() - t0
            result.add_to_manifest(
                manifest,
                name,
                out=folder / "registrations" / name,
                names=names,
                images=images,
                labels=labels,
                parameters={**result.manifest_parameters(), **options},
            )
    brain = sitk.BinaryDilate(sitk.Cast(sitk.ReadImage(labels[0]) > 0, sitk.sitkUInt8), [3] * dim)
    sitk.WriteImage(brain, str(folder / "brain_mask.nii.gz"))
    m = load_manifest(manifest)
    write_manifest(dataclasses.replace(m, mask=(folder / "brain_mask.nii.gz").absolute()), manifest)
    t0 = time.perf_counter()
    ev = _quiet(nr.evaluate, manifest, n_samples=N_SAMPLES, seed=SEED, progress=False)
    seconds["evaluate"] = time.perf_counter() - t0
    errors, per_subject = _subject_true_errors(ev, manifest, data, t1)
    return (
        ev,
        errors,
        {
            "subjects": names,
            "subject_true_error_mm": per_subject,
            "population": {"kind": kind, "dim": dim, "n": n, "seed": seed, "data": str(data)},
            "stage_seconds": {k: round(v, 1) for k, v in seconds.items()},
        },
    )


def _subject_true_errors(evaluation, manifest: Path, data_manifest: Path, rows: list[int]):
    """True correspondence error (mm) of every registration, and of every subject in it,
    inside the manifest's mask: subject i's error is the mean over the common frame's points
    p of ``|y_i - mean_j y_j|``
    (:func:`itk_nrreval.experiments.correspondence.correspondence_error`, whose mean over i it is;
    checked against it). `rows`: the registered images' entries
    of the population manifest `data_manifest` (its truth)."""
    from itk_nrreval.experiments.correspondence import correspondence_error
    from itk_nrreval.io._images import Geometry, mask_array, read_image
    from itk_nrreval.io.frame import read_chains, resampling_transform
    from itk_nrreval.io.manifest import load_manifest
    from itk_nrreval.io.transforms import chain_transform, displacement_field, invert

    truth = load_manifest(data_manifest).registrations["truth"]
    truth_grid = Geometry.from_image(read_image(truth.reference, what="truth reference"))
    to_template = [invert(chain_transform(truth.transforms[i]), grid=truth_grid) for i in rows]
    m = load_manifest(manifest)
    grid = Geometry.from_image(read_image(m.registrations[m.common_frame].reference))
    mask = mask_array(m.mask, shape=grid.shape, geometry=grid)
    per_subject = {}
    for name, scores in evaluation.scores.items():
        y = np.stack(
            [
                sitk.GetArrayFromImage(
                    displacement_field(
                        sitk.CompositeTransform(
                            [s, resampling_transform(t, scores.frame.transform)]
                        ),
                        grid,
                    )
                )[mask]
                for t, s in zip(read_chains(m, name), to_template, strict=True)
            ]
        )  # the grid points themselves cancel in y_i - mean_j y_j
        per_subject[name] = np.linalg.norm(y - y.mean(axis=0), axis=-1).mean(axis=1).tolist()
    errors = correspondence_error(evaluation, m, to_template, mask=mask)
    for name, error in errors.items():
        assert np.isclose(np.mean(per_subject[name]), error, rtol=1e-9), (name, error)
    return errors, per_subject


def _registered(case: str) -> Path:
    """The manifest of `case`'s registrations (the case is run first when it has not been)."""
    manifest = OUT / case / "manifest.yaml"
    if not (OUT / case / "truth.json").exists():
        _run_case(case)
    return manifest


def _cases() -> dict:
    """Case name -> builder(folder) -> (EvaluationResult, true error per registration)."""
    sweeps = _bench("sweeps")
    cases = {"demo": _demo, "cheat": _cheat}
    for case, kind, dim, _n, _spacing, method, engine, name, values in sweeps.CASES:
        if dim == 2:
            cases[f"sweep_{case}"] = lambda folder, k=kind, m=method, e=engine, p={name: values}: (
                _sweep(folder, kind=k, method=m, parameters=p, engine=e)
            )
    # 3D: demons field smoothing on the phantom (2 mm grid) and the MNI-based brain (3 mm
    # grid, to keep the case to minutes), 10 subjects
    for kind, spacing in (("phantom", 2.0), ("mni", 3.0)):
        cases[f"sweep_{kind}3d_fluid"] = lambda folder, k=kind, s=spacing: _sweep(
            folder,
            kind=k,
            method="fluid",
            parameters={"smoothing_mm": (1.0, 4.0, 16.0)},
            dim=3,
            n=10,
            spacing=s,
        )
    # the 2D sweeps' registrations scored on images they did not see (hypothesis a)
    for case, kind, dim, *_ in sweeps.CASES:
        if dim == 2 and case != "phantom2d_fluid_update":
            cases[f"unseen_{case}"] = lambda folder, c=case, k=kind: _unseen(
                folder, sweep_case=f"sweep_{c}", kind=k
            )
    cases["multimodal"] = _multimodal
    cases["overfit"] = lambda folder: _sweep(
        folder,
        kind="phantom",
        method="fluid",
        parameters={
            "smoothing_mm": (0.25, 1.0, 5.0),
            "iterations": ((100, 60, 40), (500, 300, 200)),
        },
    )
    cases["bspline_grids"] = lambda folder: _sweep(
        folder,
        kind="phantom",
        method="pairwise",
        parameters={"grid_spacing": (2.0, 4.0, 8.0, 16.0, 32.0, 64.0)},
    )
    cases["similar"] = lambda folder: _perturbed(
        folder,
        {
            "smooth2mm_a": _smooth_fields(1, 2.0),
            "smooth2mm_b": _smooth_fields(2, 2.0),
            "smooth4mm": _smooth_fields(3, 4.0),
        },
    )
    cases["folding"] = lambda folder: _perturbed(
        folder,
        {
            "folds": _fold_fields(4),
            "smooth2mm": _smooth_fields(5, 2.0),
            "smooth3mm": _smooth_fields(6, 3.0),
        },
    )
    # issue 41: registrations of different families to the cohort's own image 0 (the split
    # of these cases was declared before they were run: TUNING, HELD_OUT)
    families = {
        "families_mni2d": {"kind": "mni", "seed": 1},
        "families_phantom2d": {"kind": "phantom", "seed": 1},
        "families_mni2d_s2": {"kind": "mni", "seed": 2},
        "families_phantom2d_s2": {"kind": "phantom", "seed": 2},
        "families_mni2d_syn": {"kind": "mni", "seed": 3, "registrations": FAMILIES_SYN},
        "families_mni2d_n36": {"kind": "mni", "seed": 4, "n": 36},
        "families_mni3d": {"kind": "mni", "seed": 5, "dim": 3, "n": 10, "spacing": 3.0},
        "families_phantom2d_s6": {"kind": "phantom", "seed": 6},
        "families_mni2d_syn_s7": {"kind": "mni", "seed": 7, "registrations": FAMILIES_SYN},
        "families_mni2d_n24_s8": {"kind": "mni", "seed": 8, "n": 24},
        "families_mni3d_s10": {"kind": "mni", "seed": 10, "dim": 3, "n": 10, "spacing": 3.0},
        "families_phantom2d_n24_s11": {"kind": "phantom", "seed": 11, "n": 24},
        "families_mni2d_syn_s12": {"kind": "mni", "seed": 12, "registrations": FAMILIES_SYN},
        "families_mni3d_s13": {"kind": "mni", "seed": 13, "dim": 3, "n": 10, "spacing": 3.0},
        "families_mni3d_n12_s14": {"kind": "mni", "seed": 14, "dim": 3, "n": 12, "spacing": 3.0},
        "families_mni2d_s15": {"kind": "mni", "seed": 15},
        "families_mni3d_s16": {"kind": "mni", "seed": 16, "dim": 3, "n": 10, "spacing": 3.0},
        "families_phantom2d_s17": {"kind": "phantom", "seed": 17},
        "families_mni2d_syn_s18": {"kind": "mni", "seed": 18, "registrations": FAMILIES_SYN},
        "families_mni3d_s19": {"kind": "mni", "seed": 19, "dim": 3, "n": 10, "spacing": 3.0},
        "families_mni3d_n12_s20": {"kind": "mni", "seed": 20, "dim": 3, "n": 12, "spacing": 3.0},
        "families_mni2d_mix_s21": {"kind": "mni", "seed": 21, "registrations": FAMILIES_MIX},
        "families_phantom2d_mix_n16_s22": {
            "kind": "phantom",
            "seed": 22,
            "n": 16,
            "registrations": FAMILIES_MIX,
        },
        "families_mni2d_n36_s23": {"kind": "mni", "seed": 23, "n": 36},
        "families_mni2d_syn_s24": {"kind": "mni", "seed": 24, "registrations": FAMILIES_SYN},
        "families_mni3d_n12_s25": {"kind": "mni", "seed": 25, "dim": 3, "n": 12, "spacing": 3.0},
        "families_mni3d_s26": {"kind": "mni", "seed": 26, "dim": 3, "n": 10, "spacing": 3.0},
        "families_phantom2d_mix_s27": {
            "kind": "phantom",
            "seed": 27,
            "registrations": FAMILIES_MIX,
        },
        "families_mni2d_mix_n16_s28": {
            "kind": "mni",
            "seed": 28,
            "n": 16,
            "registrations": FAMILIES_MIX,
        },
        "families_mni3d_s29": {"kind": "mni", "seed": 29, "dim": 3, "n": 10, "spacing": 3.0},
        "families_mni3d_n12_s30": {"kind": "mni", "seed": 30, "dim": 3, "n": 12, "spacing": 3.0},
        "families_phantom2d_n24_s31": {"kind": "phantom", "seed": 31, "n": 24},
        "families_mni2d_mix_s32": {"kind": "mni", "seed": 32, "registrations": FAMILIES_MIX},
        "families_mni2d_span_s33": {"kind": "mni", "seed": 33, "registrations": FAMILIES_SPAN},
        "families_phantom2d_span_s34": {
            "kind": "phantom",
            "seed": 34,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni2d_span_n16_s35": {
            "kind": "mni",
            "seed": 35,
            "n": 16,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni2d_span_s36": {"kind": "mni", "seed": 36, "registrations": FAMILIES_SPAN},
        "families_phantom2d_span_n16_s37": {
            "kind": "phantom",
            "seed": 37,
            "n": 16,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni2d_span_n24_s38": {
            "kind": "mni",
            "seed": 38,
            "n": 24,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni2d_span_s39": {"kind": "mni", "seed": 39, "registrations": FAMILIES_SPAN},
        "families_phantom2d_span_s40": {
            "kind": "phantom",
            "seed": 40,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni3d_s41": {"kind": "mni", "seed": 41, "dim": 3, "n": 10, "spacing": 3.0},
        "families_mni2d_s42": {"kind": "mni", "seed": 42},
        "families_phantom2d_n16_s43": {"kind": "phantom", "seed": 43, "n": 16},
        "families_mni2d_syn_s44": {"kind": "mni", "seed": 44, "registrations": FAMILIES_SYN},
        "families_mni2d_syn_s45": {"kind": "mni", "seed": 45, "registrations": FAMILIES_SYN},
        "families_phantom2d_syn_s46": {
            "kind": "phantom",
            "seed": 46,
            "registrations": FAMILIES_SYN,
        },
        "families_mni2d_mix_n16_s47": {
            "kind": "mni",
            "seed": 47,
            "n": 16,
            "registrations": FAMILIES_MIX,
        },
        "families_mni3d_s48": {"kind": "mni", "seed": 48, "dim": 3, "n": 10, "spacing": 3.0},
        "families_mni2d_s49": {"kind": "mni", "seed": 49},
        "families_phantom2d_syn_s50": {
            "kind": "phantom",
            "seed": 50,
            "registrations": FAMILIES_SYN,
        },
        "families_mni2d_mix_s51": {"kind": "mni", "seed": 51, "registrations": FAMILIES_MIX},
        "families_mni3d_s52": {"kind": "mni", "seed": 52, "dim": 3, "n": 10, "spacing": 3.0},
        "families_mni2d_s53": {"kind": "mni", "seed": 53},
        "families_phantom2d_s54": {"kind": "phantom", "seed": 54},
        "families_mni2d_syn_s55": {"kind": "mni", "seed": 55, "registrations": FAMILIES_SYN},
        "families_phantom2d_mix_s56": {
            "kind": "phantom",
            "seed": 56,
            "registrations": FAMILIES_MIX,
        },
        "families_mni2d_span_s57": {"kind": "mni", "seed": 57, "registrations": FAMILIES_SPAN},
        "families_phantom2d_n16_s58": {"kind": "phantom", "seed": 58, "n": 16},
        "families_mni2d_s59": {"kind": "mni", "seed": 59},
        "families_phantom2d_syn_s60": {
            "kind": "phantom",
            "seed": 60,
            "registrations": FAMILIES_SYN,
        },
        "families_mni2d_mix_n16_s61": {
            "kind": "mni",
            "seed": 61,
            "n": 16,
            "registrations": FAMILIES_MIX,
        },
        "families_phantom2d_span_s62": {
            "kind": "phantom",
            "seed": 62,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni3d_s63": {"kind": "mni", "seed": 63, "dim": 3, "n": 10, "spacing": 3.0},
        "families_mni2d_s64": {"kind": "mni", "seed": 64},
        "families_phantom2d_mix_s65": {
            "kind": "phantom",
            "seed": 65,
            "registrations": FAMILIES_MIX,
        },
        "families_mni2d_syn_n16_s66": {
            "kind": "mni",
            "seed": 66,
            "n": 16,
            "registrations": FAMILIES_SYN,
        },
        "families_phantom2d_s67": {"kind": "phantom", "seed": 67},
        "families_mni2d_span_s68": {"kind": "mni", "seed": 68, "registrations": FAMILIES_SPAN},
        "families_mni3d_s69": {"kind": "mni", "seed": 69, "dim": 3, "n": 10, "spacing": 3.0},
        "families_mni2d_s70": {"kind": "mni", "seed": 70},
        "families_phantom2d_syn_s71": {
            "kind": "phantom",
            "seed": 71,
            "registrations": FAMILIES_SYN,
        },
        "families_mni2d_mix_s72": {"kind": "mni", "seed": 72, "registrations": FAMILIES_MIX},
        "families_phantom2d_span_n16_s73": {
            "kind": "phantom",
            "seed": 73,
            "n": 16,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni2d_n16_s74": {"kind": "mni", "seed": 74, "n": 16},
        "families_mni3d_s75": {"kind": "mni", "seed": 75, "dim": 3, "n": 10, "spacing": 3.0},
        "families_phantom2d_syn_s76": {
            "kind": "phantom",
            "seed": 76,
            "registrations": FAMILIES_SYN,
        },
        "families_mni2d_syn_s77": {"kind": "mni", "seed": 77, "registrations": FAMILIES_SYN},
        "families_phantom2d_mix_n16_s78": {
            "kind": "phantom",
            "seed": 78,
            "n": 16,
            "registrations": FAMILIES_MIX,
        },
        "families_mni2d_span_s79": {"kind": "mni", "seed": 79, "registrations": FAMILIES_SPAN},
        "families_phantom2d_s80": {"kind": "phantom", "seed": 80},
        "families_mni3d_s81": {"kind": "mni", "seed": 81, "dim": 3, "n": 10, "spacing": 3.0},
        "families_mni2d_span_s82": {"kind": "mni", "seed": 82, "registrations": FAMILIES_SPAN},
        "families_phantom2d_span_s83": {
            "kind": "phantom",
            "seed": 83,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni2d_span_n16_s84": {
            "kind": "mni",
            "seed": 84,
            "n": 16,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni2d_s85": {"kind": "mni", "seed": 85},
        "families_phantom2d_syn_s86": {
            "kind": "phantom",
            "seed": 86,
            "registrations": FAMILIES_SYN,
        },
        "families_phantom2d_syn_s87": {
            "kind": "phantom",
            "seed": 87,
            "registrations": FAMILIES_SYN,
        },
        "families_mni2d_span_s88": {"kind": "mni", "seed": 88, "registrations": FAMILIES_SPAN},
        "families_phantom2d_span_n16_s89": {
            "kind": "phantom",
            "seed": 89,
            "n": 16,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni2d_syn_s90": {"kind": "mni", "seed": 90, "registrations": FAMILIES_SYN},
        "families_phantom2d_mix_s91": {
            "kind": "phantom",
            "seed": 91,
            "registrations": FAMILIES_MIX,
        },
        "families_mni2d_span_n16_s92": {
            "kind": "mni",
            "seed": 92,
            "n": 16,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni2d_mix_s93": {"kind": "mni", "seed": 93, "registrations": FAMILIES_MIX},
        "families_phantom2d_s94": {"kind": "phantom", "seed": 94},
        "families_mni2d_syn_n16_s95": {
            "kind": "mni",
            "seed": 95,
            "n": 16,
            "registrations": FAMILIES_SYN,
        },
        "families_phantom2d_span_s96": {
            "kind": "phantom",
            "seed": 96,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni2d_s97": {"kind": "mni", "seed": 97},
        "families_phantom2d_syn_s98": {
            "kind": "phantom",
            "seed": 98,
            "registrations": FAMILIES_SYN,
        },
        "families_mni2d_span_s99": {"kind": "mni", "seed": 99, "registrations": FAMILIES_SPAN},
        "families_phantom2d_mix_s100": {
            "kind": "phantom",
            "seed": 100,
            "registrations": FAMILIES_MIX,
        },
        "families_mni2d_n16_s101": {"kind": "mni", "seed": 101, "n": 16},
        "families_phantom2d_span_n16_s102": {
            "kind": "phantom",
            "seed": 102,
            "n": 16,
            "registrations": FAMILIES_SPAN,
        },
        "families_mni2d_syn_s103": {"kind": "mni", "seed": 103, "registrations": FAMILIES_SYN},
        "families_phantom2d_s104": {"kind": "phantom", "seed": 104},
        "families_mni3d_s105": {"kind": "mni", "seed": 105, "dim": 3, "n": 10, "spacing": 3.0},
        "families_mni2d_s106": {"kind": "mni", "seed": 106},
        "families_mni3d_n12_s107": {"kind": "mni", "seed": 107, "dim": 3, "n": 12, "spacing": 3.0},
        "families_mni2d_span_n16_s108": {
            "kind": "mni",
            "seed": 108,
            "n": 16,
            "registrations": FAMILIES_SPAN,
        },
        "families_phantom2d_s109": {"kind": "phantom", "seed": 109},
        "families_mni2d_n16_s110": {"kind": "mni", "seed": 110, "n": 16},
        "families_mni2d_fold_s111": {"kind": "mni", "seed": 111, "registrations": FAMILIES_FOLD},
        "families_phantom2d_fold_s112": {
            "kind": "phantom",
            "seed": 112,
            "registrations": FAMILIES_FOLD,
        },
        "families_mni2d_fold_n16_s113": {
            "kind": "mni",
            "seed": 113,
            "n": 16,
            "registrations": FAMILIES_FOLD,
        },
        "families_phantom2d_fold_s114": {
            "kind": "phantom",
            "seed": 114,
            "registrations": FAMILIES_FOLD,
        },
        "families_mni2d_fold_s115": {"kind": "mni", "seed": 115, "registrations": FAMILIES_FOLD},
        "families_phantom2d_fold_s116": {
            "kind": "phantom",
            "seed": 116,
            "registrations": FAMILIES_FOLD,
        },
        "families_mni2d_fold_s117": {"kind": "mni", "seed": 117, "registrations": FAMILIES_FOLD},
        "families_phantom2d_fold_n16_s118": {
            "kind": "phantom",
            "seed": 118,
            "n": 16,
            "registrations": FAMILIES_FOLD,
        },
    }
    for case, spec in families.items():
        cases[case] = lambda folder, spec=spec: _families(folder, **spec)
        cases[SECOND_SCAN[case]] = lambda folder, c=case, spec=spec: _second_scan(
            folder,
            case=c,
            registered=_registered(c),
            data=_population(
                spec["kind"],
                dim=spec.get("dim", 2),
                n=spec.get("n", N),
                spacing=spec.get("spacing"),
                seed=spec["seed"],
                contrasts=("t1", "t2"),
            ),
        )
    return cases


# ---------------------------------------------------------------------------- run and judge


def _run_case(case: str) -> None:
    """Register and evaluate one case; save what a re-judged verdict needs."""
    folder = OUT / case
    # a case is run afresh: the demo refuses a folder holding this benchmark's own files
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    t0 = time.perf_counter()
    evaluation, errors, *more = _cases()[case](folder)
    (folder / "evaluation.pkl").write_bytes(pickle.dumps(evaluation))
    (folder / "results.json").write_text(json.dumps(evaluation.to_dict(), indent=1) + "\n")
    truth = {"true_error_mm": errors, **(more[0] if more else {})}
    truth["seconds"] = round(time.perf_counter() - t0, 1)
    (folder / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    if "subject_true_error_mm" in truth:  # for a subject-QC benchmark (issue 42)
        per = truth["subject_true_error_mm"]
        lines = ["subject,registration,true_error_mm"] + [
            f"{subject},{name},{e:.4f}"
            for name, errors in per.items()
            for subject, e in zip(truth["subjects"], errors, strict=True)
        ]
        (folder / "subject_true_errors.csv").write_text("\n".join(lines) + "\n")
    print(f"[verdict] {case}: {truth['seconds']:.0f} s", flush=True)


def manifest_of(case: str) -> Path:
    """The manifest a saved case was scored from."""
    if case == "cheat":
        return OUT / "demo" / "manifest_cheat.yaml"
    if case == "multimodal":
        return OUT / case / "data" / "manifest.yaml"
    for path in (OUT / case / "manifest.yaml", OUT / case / "sweep" / "manifest.yaml"):
        if path.exists():
            return path
    raise FileNotFoundError(f"{case}: no manifest in {OUT / case}")


#: The sweeps' second scans: each, as its sweep, one family (settings of one method).
_SWEEP_SECOND_SCANS = {scan for case, scan in SECOND_SCAN.items() if case.startswith("sweep_")}


def families_of(case: str) -> dict[str, tuple | None]:
    """Each registration's family in a saved case, as ``evaluate`` records it today:
    ``(method, engine)`` from the manifest's ``parameters``, None where they are not given.
    A sweep's registrations, and their second scan's, are one family (``("sweep",)``): the
    sweeps saved here were made before sweeps recorded method and engine."""
    from itk_nrreval.evaluation import _registration_family
    from itk_nrreval.io.manifest import load_manifest

    manifest = _quiet(load_manifest, manifest_of(case))
    if case.startswith("sweep_") or case in _SWEEP_SECOND_SCANS:
        return dict.fromkeys(manifest.registrations, ("sweep",))
    return {name: _registration_family(reg) for name, reg in manifest.registrations.items()}


def _load(case: str, *, description_length: bool = False):
    """The saved :class:`~itk_nrreval.EvaluationResult` of a case, its registrations'
    families as today's ``evaluate`` would record them (:func:`families_of`; evaluations saved
    before scores carried families have None). With `description_length`, each score carries
    the case's description length, as ``evaluate(description_length=True)`` measured it
    (``bench_description_length.py --compute``: ``description_length.json``), where measured."""
    import dataclasses

    with open(OUT / case / "evaluation.pkl", "rb") as saved:
        evaluation = _RenamingUnpickler(saved).load()
    family = families_of(case)
    lengths = {}
    if description_length and (OUT / case / "description_length.json").exists():
        record = json.loads((OUT / case / "description_length.json").read_text())
        lengths = _bench("description_length").description_lengths(record)
    scores = {
        name: dataclasses.replace(
            score, family=family.get(name), description_length=lengths.get(name)
        )
        for name, score in evaluation.scores.items()
    }
    return dataclasses.replace(evaluation, scores=scores)


def _verdict(case: str, *, labels: bool = True, evaluation=None):
    """The verdict of a saved case, recomputed by today's :func:`verdict`; with
    ``labels=False`` as if the case had no label maps (specificity and folding alone)."""
    from itk_nrreval.evaluation import _judged

    evaluation = _load(case) if evaluation is None else evaluation
    has_labels = labels and any(s.overlap for s in evaluation.scores.values())
    return _judged(evaluation.scores, evaluation.comparisons, has_labels=has_labels)


def _overlap_says(evaluation, better: str, worse: str) -> str:
    """What the inverse-volume overlap says of a pair whose true errors order it `better`,
    `worse`: ``"agrees"`` or ``"contradicts"`` (a separable difference, subject-level
    interval), ``"not separable"``, or ``"-"`` (no overlap)."""
    measure = "overlap.inverse_volume"
    for c in evaluation.comparisons:
        if c.measure == measure and {c.a, c.b} == {better, worse}:
            if not c.separable:
                return "not separable"
            better_minus_worse = c.difference if c.a == better else -c.difference
            return "agrees" if better_minus_worse > 0 else "contradicts"
    return "-"


def judge(case: str, *, labels: bool = True, description_length: bool = False) -> list[dict]:
    """Every pair of registrations of a saved case, with the verdict's decision and outcome
    (``labels=False``: the verdict without the overlap; `description_length`: with the case's
    description length where measured, :func:`_load`), and what the overlap says of the pair
    against the truth (``overlap``: with labels only; where it contradicts the truth, open is
    the right answer)."""
    errors = json.loads((OUT / case / "truth.json").read_text())["true_error_mm"]
    evaluation = _load(case, description_length=description_length)
    v = _verdict(case, labels=labels, evaluation=evaluation)
    decided = {(d.better, d.worse): d.basis for d in v.decisions}
    leans = {frozenset((p.a, p.b)): p.leans_to for p in v.open_pairs if p.leans_to}
    rows = []
    for a, b in itertools.combinations(errors, 2):
        if errors[b] < errors[a]:
            a, b = b, a  # a: the lower true error
        judged = errors[b] - errors[a] > MARGIN * errors[a]
        if (a, b) in decided:
            decision, basis, outcome = f"{a} > {b}", decided[(a, b)], "right"
        elif (b, a) in decided:
            decision, basis, outcome = f"{b} > {a}", decided[(b, a)], "wrong"
        else:
            decision, basis, outcome = "open", "", "open"
        lean = leans.get(frozenset((a, b)))
        lean = "" if lean is None else ("right" if lean == a else "wrong")
        if not judged:
            outcome = "near-tie, " + ("open" if outcome == "open" else "decided")
            lean = "near-tie" if lean else ""
        rows.append(
            {
                "case": case,
                "a": a,
                "b": b,
                "true_error_a_mm": round(errors[a], 4),
                "true_error_b_mm": round(errors[b], 4),
                "decision": decision,
                "basis": basis,
                "outcome": outcome,
                "overlap": _overlap_says(evaluation, a, b) if labels else "-",
                "lean": lean,  # an open pair's OpenPair.leans_to against the truth
            }
        )
    return rows


def _counts(rows: list[dict]) -> dict[str, int]:
    keys = ("right", "wrong", "open", "near-tie, decided", "near-tie, open")
    return {k: sum(r["outcome"] == k for r in rows) for k in keys}


def _write(rows: list[dict], cases: list[str], unlabelled: list[dict], suffix: str = "") -> dict:
    OUT.mkdir(parents=True, exist_ok=True)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]) if rows else ["case"])
    writer.writeheader()
    writer.writerows(rows)
    (OUT / f"pairs{suffix}.csv").write_text(buffer.getvalue())
    (OUT / f"pairs{suffix}.json").write_text(json.dumps(rows, indent=1) + "\n")
    counts = {c: _counts([r for r in rows if r["case"] == c]) for c in cases}
    counts["overall"] = _counts(rows)
    alone = {c: _counts([r for r in unlabelled if r["case"] == c]) for c in cases}
    alone["overall"] = _counts(unlabelled)
    lines = [
        f"Pairs whose true errors differ by more than {MARGIN:.0%}: right / wrong / open; "
        "near-ties (closer than that): decided / open. Without labels: the same verdict "
        "without the overlap (specificity and folding alone).",
        "",
        "| case | right | wrong | open | near-ties decided | near-ties open "
        "| without labels: right / wrong / open |",
        "|---|--:|--:|--:|--:|--:|--:|",
    ]
    for c, k in counts.items():
        name = f"**{c}**" if c == "overall" else c
        u = alone[c]
        lines.append(
            f"| {name} | {k['right']} | {k['wrong']} | {k['open']} | "
            f"{k['near-tie, decided']} | {k['near-tie, open']} | "
            f"{u['right']} / {u['wrong']} / {u['open']} |"
        )
    lines += ["", "Wrong decisions:", ""]
    lines += [
        f"- {r['case']}: {r['decision']} ({r['basis']}); true errors {r['a']} "
        f"{r['true_error_a_mm']:.2f} mm, {r['b']} {r['true_error_b_mm']:.2f} mm"
        for r in rows
        if r["outcome"] == "wrong"
    ] or ["- none"]
    text = "\n".join(lines) + "\n"
    (OUT / f"summary{suffix}.md").write_text(text)
    print(text)
    return {"counts": counts, "counts_without_labels": alone, "pairs": rows}


def split_and_second_scans(split: str) -> list[str]:
    """The cases of `split` (:data:`SPLIT_CASES`), each followed by its second scan where it
    has one: the order in which they can run."""
    return [c for case in SPLIT_CASES[split] for c in (case, SECOND_SCAN.get(case)) if c]


def split_of(case: str) -> str:
    """The declared split of a case or of its second scan: one of :data:`SPLITS`."""
    base = {v: k for k, v in SECOND_SCAN.items()}.get(case, case)
    for split, cases in SPLIT_CASES.items():
        if base in cases:
            return split
    raise AssertionError(f"{case} is in no split")


#: The three modes of issue 41, plus the second scan with labels: (title, second scan?,
#: labels?).
MODES = (
    ("with labels", False, True),
    ("without labels", False, False),
    ("second scan, without labels", True, False),
    ("second scan, with labels", True, True),
)


def _write_splits(
    rows: list[dict], unlabelled: list[dict], cases: list[str], suffix: str = ""
) -> dict:
    """Per case and per split (:data:`TUNING`, :data:`HELD_OUT`), right / wrong / open in
    each mode (:data:`MODES`); ``splits.md`` and ``splits.json``. A case's second scan counts
    only where it was judged in the same run."""
    bases = [c for c in cases if c in DECLARED]
    table = {}
    for case in bases:
        table[case] = {}
        for title, second, labels in MODES:
            judged = SECOND_SCAN.get(case) if second else case
            if judged not in cases:
                continue
            source = [r for r in (rows if labels else unlabelled) if r["case"] == judged]
            table[case][title] = _counts(source)
            table[case][title]["open, overlap contradicts"] = sum(
                r["outcome"] == "open" and r["overlap"] == "contradicts" for r in source
            )
            for lean in ("right", "wrong"):
                table[case][title][f"leans {lean}"] = sum(r["lean"] == lean for r in source)
    keys = ("right", "wrong", "open", "open, overlap contradicts", "leans right", "leans wrong")
    totals = {}
    for split in SPLITS:
        totals[split] = {}
        for title, *_ in MODES:
            cells = [t[title] for c, t in table.items() if split_of(c) == split and title in t]
            if cells:
                totals[split][title] = {k: sum(x[k] for x in cells) for k in keys}

    def cell(k: dict | None) -> str:
        if not k:
            return "-"
        contradicted = (
            f" ({k['open, overlap contradicts']})" if k["open, overlap contradicts"] else ""
        )
        return f"{k['right']} / {k['wrong']} / {k['open']}{contradicted}"

    header = "| case | split | " + " | ".join(t for t, *_ in MODES) + " |"
    lines = [
        "Right / wrong / open over the pairs whose true errors differ by more than "
        f"{MARGIN:.0%} (near-ties left out), today's verdict; in brackets, of the open "
        "pairs, those where the label overlap separably contradicts the true error (there "
        "open is the right answer with labels).",
        "",
        header,
        "|---|---|" + "--:|" * len(MODES),
    ]
    for split in SPLITS:
        for c, t in table.items():
            if split_of(c) == split:
                cells = " | ".join(cell(t.get(title)) for title, *_ in MODES)
                lines.append(f"| {c} | {split} | {cells} |")
        if totals.get(split):
            cells = " | ".join(f"**{cell(totals[split].get(title))}**" for title, *_ in MODES)
            lines.append(f"| **{split}** | | {cells} |")
    lines += [
        "",
        "Of the open pairs, those that lean one way (`OpenPair.leans_to`: the smoother-fields "
        "rule across families, not a decision), leaning right / wrong:",
        "",
        "| split | " + " | ".join(t for t, *_ in MODES) + " |",
        "|---|" + "--:|" * len(MODES),
    ]
    for split, t in totals.items():
        if t:
            leans = [t.get(title) for title, *_ in MODES]
            cells = [f"{k['leans right']} / {k['leans wrong']}" if k else "-" for k in leans]
            lines.append(f"| {split} | {' | '.join(cells)} |")
    text = "\n".join(lines) + "\n"
    (OUT / f"splits{suffix}.md").write_text(text)
    (OUT / f"splits{suffix}.json").write_text(
        json.dumps({"cases": table, "totals": totals}, indent=1) + "\n"
    )
    print(text)
    return {"cases": table, "totals": totals}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK)}")
    parser.add_argument("--cases", help="comma-separated case names (default: all)")
    parser.add_argument(
        "--splits",
        help="comma-separated split names (SPLITS: tuning, held-out, fresh, fresh2, ...): "
        "their cases, each before its second scan",
    )
    parser.add_argument(
        "--rejudge",
        action="store_true",
        help="recompute only the verdict from the saved evaluations (no registration)",
    )
    parser.add_argument(
        "--description-length",
        action="store_true",
        help="judge each saved case with its description length where measured "
        "(bench_description_length.py --compute), as evaluate(description_length=True) "
        "would; the tables go to *_description_length.md",
    )
    parser.add_argument(
        "--new",
        action="store_true",
        help="only the cases of issue 41 (families_*) and their second scans",
    )
    parser.add_argument(
        "--missing",
        action="store_true",
        help="only the cases not saved yet (benchmarks/out/ is not in the repository: on a "
        "new machine, every case), each before its second scan",
    )
    args = parser.parse_args([] if argv is None else argv)
    known = list(_cases())  # each case before its second scan
    new = [c for c in known if "families_" in c]
    cases = args.cases.split(",") if args.cases else list(QUICK if args.quick else known)
    if args.splits:
        unknown = [s for s in args.splits.split(",") if s not in SPLIT_CASES]
        if unknown:
            parser.error(f"unknown split(s) {', '.join(unknown)}; known: {', '.join(SPLITS)}")
        cases = [c for s in args.splits.split(",") for c in split_and_second_scans(s)]
    cases = new if args.new and not args.cases else cases
    if args.missing:
        cases = [c for c in cases if not (OUT / c / "evaluation.pkl").exists()]
    unknown = [c for c in cases if c not in known]
    if unknown:
        parser.error(f"unknown case(s) {', '.join(unknown)}; known: {', '.join(known)}")
    if args.rejudge:
        missing = [c for c in cases if not (OUT / c / "evaluation.pkl").exists()]
        if missing:
            print(f"[verdict] not run yet, left out: {', '.join(missing)}", flush=True)
    else:
        for case in cases:
            _run_case(case)
    # The tables always cover every saved case (judged by today's verdict), so that running
    # or rejudging a few cases does not leave summary.md and splits.md with those alone.
    cases = [c for c in known if (OUT / c / "evaluation.pkl").exists()]
    dl = args.description_length
    rows = [row for case in cases for row in judge(case, description_length=dl)]
    unlabelled = [row for case in cases for row in judge(case, labels=False, description_length=dl)]
    suffix = "_description_length" if dl else ""
    result = _write(rows, cases, unlabelled, suffix)
    result["splits"] = _write_splits(rows, unlabelled, cases, suffix)
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
