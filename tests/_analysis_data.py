"""A tiny HalfCheetah study and test-phase folder shared by the analysis tests.

Built once per pytest session on disk (under pytest's base temp folder), whichever of
test_report.py, test_video.py or test_notebooks.py asks first: the builder is idempotent, so
each module's fixture can call it.
"""

from __future__ import annotations

import contextlib
import io
import json
from dataclasses import dataclass
from pathlib import Path

import pytest

STUDY_NAME = "tiny-hc"
TEST_SEEDS = (10, 11)
STEPS = 2048  # PPO's default rollout: the smallest budget; two HalfCheetah episodes


@dataclass(frozen=True)
class TinyStudy:
    """Paths of the shared tiny study."""

    root: Path
    storage: str
    study_name: str
    runs: Path


def build_tiny_study(base: Path) -> TinyStudy:
    """Evolve 4 trials and run a 2-seed test phase of HalfCheetah-v5 (velocities), once."""
    root = base / "ermrl_analysis_tiny"
    root.mkdir(parents=True, exist_ok=True)
    db = root / "study.db"
    storage = f"sqlite:///{db}"
    runs = root / "runs" / STUDY_NAME
    done = root / "done.json"
    tiny = TinyStudy(root=root, storage=storage, study_name=STUDY_NAME, runs=runs)
    if done.exists():
        return tiny
    from ermrl.cli import evolve_main, test_main

    common = ["--storage", storage, "--study-name", STUDY_NAME, "--quiet"]
    with contextlib.redirect_stderr(io.StringIO()):
        code = evolve_main(
            [
                "--env-id",
                "HalfCheetah-v5",
                "--observe",
                "velocities",
                "--n-trials",
                "4",
                "--n-seeds",
                "1",
                "--training-steps",
                str(STEPS),
                "--units",
                "20",
                "--sampler-seed",
                "0",
                "--ppo",
                "n_steps=1024",
                "n_epochs=2",
                *common,
            ]
        )
        if code != 0:
            pytest.fail(f"tiny evolve failed with exit code {code}")
        code = test_main(
            [
                "--training-steps",
                str(STEPS),
                "--seeds",
                *map(str, TEST_SEEDS),
                "--out",
                str(runs),
                *common,
            ]
        )
        if code != 0:
            pytest.fail(f"tiny test phase failed with exit code {code}")
    done.write_text(json.dumps({"study": STUDY_NAME, "storage": storage, "runs": str(runs)}))
    return tiny


def assert_self_contained_html(page: Path, elsewhere: Path) -> str:
    """Move ``page`` alone to ``elsewhere`` and check that it needs no other file.

    Every ``src`` is a ``data:image/png`` URI whose bytes are a PNG, and no ``href`` names a
    local file. Returns the page's text (read from its new place).
    """
    import base64
    import re
    from html.parser import HTMLParser

    elsewhere.mkdir(parents=True, exist_ok=True)
    moved = page.rename(elsewhere / page.name)
    text = moved.read_text()
    attrs: list[tuple[str, str, str]] = []

    class Collect(HTMLParser):
        def handle_starttag(self, tag: str, items: list[tuple[str, str | None]]) -> None:
            attrs.extend((tag, k, v or "") for k, v in items if k in ("src", "href"))

    Collect().feed(text)
    images = [v for tag, k, v in attrs if tag == "img" and k == "src"]
    assert images, "the page has no figure"
    for tag, key, value in attrs:
        if key == "src":
            assert tag == "img" and value.startswith("data:image/png;base64,"), value[:80]
            assert base64.b64decode(value.split(",", 1)[1]).startswith(b"\x89PNG\r\n\x1a\n")
        else:
            assert re.match(r"^[a-z][a-z0-9+.-]*:|^#", value), f"link to a local file: {value}"
    assert 'src="' not in re.sub(r'src="data:[^"]*"', "", text)
    return text
