"""Shared fixtures: small synthetic sequences with exact ground truth (no real data needed).

``python -m pytest -m "not slow"`` runs the quick suite (under a minute on 2 cores); ``python -m pytest`` runs
everything (under 10 minutes). Mark a test ``@pytest.mark.slow`` when it takes seconds (see setup.cfg).
"""

from pathlib import Path

import pytest

from tambridge.io.synthetic import SynthOptions, write_synthetic_sequence


@pytest.fixture(scope="session")
def synthetic_sequence_dir(tmp_path_factory) -> Path:
    """A noise-free 30-frame 160x120 closed-loop sequence in the TUM layout (written once per session)."""
    folder = tmp_path_factory.mktemp("synthetic") / "room"
    write_synthetic_sequence(folder, SynthOptions(frame_count=30, width=160, height=120))
    return folder
