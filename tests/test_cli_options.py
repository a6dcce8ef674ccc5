"""Options shared by the sub-commands mean the same everywhere."""

from __future__ import annotations

import pytest

from itk_nrreval.cli import build_parser

# The sub-commands that do long work, with the least they need to parse.
LONG_WORK = {
    "evaluate": ["m.yaml", "--out", "o"],
    "register": ["--images", "a.nii.gz", "b.nii.gz", "--method", "affine", "--out", "o"],
    "validate": ["m.yaml", "--out", "o"],
    "sweep": [
        "--images",
        "a",
        "b",
        "--method",
        "fluid",
        "--param",
        "smoothing_mm=1,2",
        "--out",
        "o",
    ],
    "diagnose": ["m.yaml", "--registration", "r", "--out", "o"],
    "overlap": ["a.nii.gz", "b.nii.gz"],
    "specificity": ["a.nii.gz", "b.nii.gz"],
}


@pytest.mark.parametrize("command", sorted(LONG_WORK))
@pytest.mark.parametrize("flag", ["--quiet", "--no-progress"])
def test_every_long_command_takes_quiet_and_its_alias(command, flag):
    parser = build_parser()
    base = [command, *LONG_WORK[command]]
    assert parser.parse_args(base).quiet is False
    assert parser.parse_args([*base, flag]).quiet is True
