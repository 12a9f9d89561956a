"""Fixtures of the end-to-end tests: a small synthetic session (made once per test run and copied
per module), and a screenshot in test-artifacts/ for every failed test that has a page."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from viser_helpers import save_screenshot

FRAMES = 40
REFERENCE_STEP = 10


@pytest.fixture(scope="session")
def synthetic_data(tmp_path_factory) -> Path:
    """A 40-frame 320x240 synthetic MSRA-layout sequence (with ground truth for the screenshot)."""
    from handanno_core.synth import generate_sequence

    out = tmp_path_factory.mktemp("e2e-data") / "data"
    generate_sequence(out, frames=FRAMES, seed=0, progress=False)
    return out


def make_session(folder: Path, data: Path) -> Path:
    """A session over ``data`` with references every 10th frame (no descriptor pass: fast)."""
    from handanno_core.pipeline import new_session

    session = new_session(folder, data, format="msra", overwrite=True)
    refs = list(range(0, session.num_frames, REFERENCE_STEP))
    parent = [-1 if f in refs else f - f % REFERENCE_STEP for f in range(session.num_frames)]
    session.set_selection({"strategy": "uniform", "reference_frames": refs, "parent": parent})
    session.close()
    return folder


@pytest.fixture(scope="module")
def session_folder(synthetic_data, tmp_path_factory) -> Path:
    return make_session(tmp_path_factory.mktemp("e2e-session") / "sess", synthetic_data)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.when == "call" and report.failed:
        for value in item.funcargs.values():
            page = getattr(value, "page", None)
            if page is not None:
                try:
                    path = save_screenshot(page, f"{item.name}.png")
                    report.sections.append(("screenshot", str(path)))
                except Exception:
                    pass


def pytest_collection_modifyitems(items):
    for item in items:
        if "tests/e2e/" in str(item.fspath).replace("\\", "/"):
            item.add_marker(pytest.mark.e2e)


@pytest.fixture(scope="session", autouse=True)
def _clean_artifacts():
    yield
    art = Path(__file__).resolve().parents[2] / "test-artifacts"
    if art.exists() and not any(art.iterdir()):
        shutil.rmtree(art, ignore_errors=True)
