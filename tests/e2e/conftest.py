"""Fixtures of the end-to-end tests: a small synthetic session (made once per test run and copied
per module), failure artifacts under the pytest temp dir, and the opt-in README screenshots.

Options (``pytest tests/e2e ...``; README.md in this folder):

* ``--screenshots DIR``: also write the README screenshots into DIR (same as
  ``HANDANNO_SCREENSHOTS=DIR``). Without it no test writes outside the pytest temp dir.
* ``--e2e-trace``: record a Playwright trace per page, saved next to the failure screenshot.

On a failure every open page is screenshotted (and its browser console saved) into
``<pytest temp root>/e2e-failures/<pytest-N>/`` (e.g. /tmp/pytest-of-root/e2e-failures/pytest-7/);
the report names the files.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import viser_helpers

FRAMES = 40
REFERENCE_STEP = 10


def pytest_addoption(parser):
    group = parser.getgroup("handanno e2e")
    group.addoption(
        "--screenshots",
        metavar="DIR",
        default=None,
        help="also write the README screenshots of the e2e tests into DIR",
    )
    group.addoption(
        "--e2e-trace",
        action="store_true",
        default=False,
        help="record a Playwright trace per page; saved with the screenshot on failure",
    )


def pytest_configure(config):
    # Only reached when this conftest is loaded at start-up (``pytest tests/e2e``); a plain
    # ``pytest`` from the root loads it later and uses the environment variables instead.
    out = config.getoption("--screenshots", default=None)
    if out:
        os.environ["HANDANNO_SCREENSHOTS"] = str(Path(out).resolve())
    if config.getoption("--e2e-trace", default=False):
        viser_helpers.TRACE = True


@pytest.fixture(scope="session", autouse=True)
def _failure_artifacts_dir(tmp_path_factory):
    # next to the pytest-N folders, not in one: pytest deletes all but the last three of those,
    # which concurrent runs on a shared machine reach within minutes
    base = tmp_path_factory.getbasetemp()
    if base.name.startswith("popen-gw"):  # pytest-xdist: <root>/pytest-N/popen-gwK per process
        base = base.parent.parent / f"{base.parent.name}-{base.name.removeprefix('popen-')}"
    viser_helpers.ARTIFACTS = base.parent / "e2e-failures" / base.name


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
    if report.failed and report.when in ("setup", "call"):
        # pages of module fixtures are still open here; pages of a test's own ``with browser()``
        # were saved by browser() as the exception left it
        saved = viser_helpers.save_failure_artifacts(f"{item.name}-{report.when}")
        if saved or viser_helpers.ARTIFACTS.exists():
            report.sections.append(
                (
                    "e2e failure artifacts",
                    "\n".join(map(str, saved)) or str(viser_helpers.ARTIFACTS),
                )
            )


def pytest_collection_modifyitems(items):
    for item in items:
        if "tests/e2e/" in str(item.fspath).replace("\\", "/"):
            item.add_marker(pytest.mark.e2e)
