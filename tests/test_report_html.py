"""The HTML of a report page (``report.html``, ``docs/reproduction.html``): rendered from its
Markdown by Python-Markdown, so no Markdown syntax or Python literal is left in the page."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from ermrl.analysis._report import _Doc  # noqa: E402


def _doc() -> _Doc:
    doc = _Doc()
    doc.h(1, "Reproducing *Evolving Reservoirs for Meta Reinforcement Learning*")
    doc.p(
        "**How verdicts are decided.** A comparison is *supported* when `ermrl reproduction` "
        "says so ([arXiv:2312.06695](https://arxiv.org/abs/2312.06695), "
        "[the seeds](runs/demo/seeds.csv)); n=2 < 5 and <script>alert(1)</script> stay text."
    )
    doc.table(
        pd.DataFrame(
            {
                "agent": ["**res-ppo**", "ppo"],
                "verdict": ["*supported*", "inconclusive"],
                "< 5 seeds": [False, True],
            }
        )
    )
    doc.code("ermrl run experiments/demo.yaml", "bash")
    doc.bullets(["**H1** CartPole", "[result](runs/demo/result.json)"])
    return doc


def _visible_text(page: str) -> str:
    """The text a browser shows (tags removed, entities decoded)."""
    parts: list[str] = []

    class Text(HTMLParser):
        def handle_data(self, data: str) -> None:
            parts.append(data)

    body = page.split("<body>", 1)[1]
    Text(convert_charrefs=True).feed(body)
    return "".join(parts)


def test_html_renders_markdown_and_booleans_as_yes_no() -> None:
    page = _doc().html("reproduction")
    text = _visible_text(page)
    assert "*" not in text and "`" not in text and "](" not in text
    assert not re.search(r"\bFalse\b|\bTrue\b", text)
    assert (
        "<h1>Reproducing <em>Evolving Reservoirs for Meta Reinforcement Learning</em></h1>" in page
    )
    assert "<strong>How verdicts are decided.</strong>" in page
    assert "<em>supported</em>" in page
    assert "<code>ermrl reproduction</code>" in page
    assert '<a href="https://arxiv.org/abs/2312.06695">arXiv:2312.06695</a>' in page
    assert '<a href="runs/demo/seeds.csv">the seeds</a>' in page
    assert "<td><strong>res-ppo</strong></td>" in page and "<td><em>supported</em></td>" in page
    cells = re.findall(r"<td>(yes|no)</td>", page)
    assert cells == ["no", "yes"]
    assert "<th>&lt; 5 seeds</th>" in page
    assert "<li><strong>H1</strong> CartPole</li>" in page
    assert re.search(r"<pre><code[^>]*>ermrl run experiments/demo.yaml\n</code></pre>", page)
    # Raw HTML in the text is shown, never run.
    assert "<script>" not in page and "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert "n=2 &lt; 5" in page


def test_markdown_tables_print_booleans_as_yes_no() -> None:
    md = _doc().markdown()
    assert "| **res-ppo** | *supported* | no |" in md
    assert "False" not in md and "True" not in md


def test_self_contained_html_embeds_figures_and_writes_local_links_as_text(tmp_path: Path) -> None:
    fig, ax = plt.subplots(figsize=(1, 1))
    ax.plot([0, 1])
    (tmp_path / "test").mkdir()
    fig.savefig(tmp_path / "test" / "curve.png")
    plt.close(fig)
    doc = _doc()
    doc.img("test/curve.png", "Learning curves")
    page = doc.html("report", embed=tmp_path)
    hrefs = re.findall(r'href="([^"]*)"', page)
    assert hrefs == ["https://arxiv.org/abs/2312.06695"]  # local links are text
    assert "the seeds (<code>runs/demo/seeds.csv</code>)" in page
    assert "result (<code>runs/demo/result.json</code>)" in page
    assert re.search(r'<img src="data:image/png;base64,[^"]+" alt="Learning curves">', page)
    assert "*" not in _visible_text(page)
