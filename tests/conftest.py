import os
from pathlib import Path

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

FIXTURES = Path(__file__).resolve().parents[2] / "shared" / "fixtures"


@pytest.fixture(scope="session")
def fixtures_dir() -> Path:
    """Real files from other tools (../shared/fixtures); tests that need them skip when absent."""
    if not FIXTURES.is_dir():
        pytest.skip(f"shared fixtures not found at {FIXTURES}")
    return FIXTURES


@pytest.fixture(scope="session")
def quick_demo(tmp_path_factory) -> Path:
    """A small demo folder (data/, demo.tracemap, export/) built once per test session. Treat as read-only:
    copy the project (`shutil.copytree`) before changing it."""
    from engine.demo import DEMO_OUTCROP, run_demo
    from engine.synthetic import QUICK

    out = tmp_path_factory.mktemp("quick_demo")
    run_demo(out, seed=3, outcrop_settings={**DEMO_OUTCROP, **QUICK}, say=lambda m: None)
    return out
