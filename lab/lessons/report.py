"""Headless lesson runs: ``vision-lab lesson run LESSON --report DIR``.

Runs the lesson's reference pipeline, with no browser, on one of the lesson's check datasets (its
first by default, with seed 0 unless given) and writes into ``DIR``:

``index.html``
    the lesson's title and text, a table of every step with its time and metrics, the images
    (each image set's first views with their 2D overlays, plots), and the 3D scene embedded;
``scene.html``
    the saved 3D scene (viser's ``scene.as_html()`` through :func:`lab.viewer.export.export_scene`),
    one self-contained file;
``scene.png``
    its poster: the scene as the page's initial camera sees it, drawn without a browser. The page shows
    it at once where the scene goes (the interactive page takes about 15 s to show anything in
    software-rendered chromium, issue 16) and loads the interactive scene in its place when asked, with
    a "loading the 3D scene" note over the poster until it has loaded;
``images/*.png`` and ``report.json`` (the run's records: steps, controls, seconds, metrics).
"""

from __future__ import annotations

import html
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lab.core.errors import LabError, UnknownName
from lab.core.pipeline import RunRecord, Session, _jsonable, open_session
from lab.core.values import Curve, Image, ImageSet
from lab.lessons.format import Lesson

#: Views of each image set shown in the report.
VIEWS_SHOWN = 4


@dataclass
class LessonRun:
    """What a headless run did: the session, its records, and the error that stopped it (if any)."""

    session: Session
    dataset: str
    options: dict[str, Any]
    seed: int
    records: list[RunRecord] = field(default_factory=list)
    error: str = ""


def run_lesson(lesson: Lesson, *, dataset: str | None = None, seed: int = 0) -> LessonRun:
    """Run the lesson's reference pipeline (every step, in the planner's order) on a check dataset (by
    its name in tasks.toml) or a module dataset; stops at the first step that fails."""
    pipeline = lesson.pipeline
    if dataset is None or dataset in lesson.datasets:
        data = lesson.datasets[dataset] if dataset else next(iter(lesson.datasets.values()))
        name, options, params = data.dataset, dict(data.options), data.params
    else:
        try:
            name, options, params = pipeline.dataset(dataset).name, {}, {}
        except UnknownName:
            raise UnknownName("--dataset", f"no dataset {dataset!r}: the lesson's are "
                                           f"{sorted(lesson.datasets)}, "
                                           f"the module's {[d.name for d in pipeline.datasets]}") from None
    spec = pipeline.dataset(name)
    if any(o.name == "seed" for o in spec.options):
        options["seed"] = int(seed)
    session = open_session(pipeline, name, options, seed=int(seed))
    run = LessonRun(session=session, dataset=name, options=options, seed=int(seed))
    plan = session.plan(None, params)  # every step: "Run all" on a fresh session
    try:
        session.run_plan(plan, params, on_step=run.records.append)
    except LabError as exc:
        run.error = f"step {plan.steps[len(run.records)]} failed: {exc.reason}"
    return run


def write_report(lesson: Lesson, out_dir: Path | str, *, dataset: str | None = None, seed: int = 0) -> Path:
    """Run the lesson headless and write the report; returns the path of ``index.html``."""
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    run = run_lesson(lesson, dataset=dataset, seed=seed)
    pictures = _write_pictures(run.session, out / "images")
    scene_note = _write_scene(run.session, out)
    (out / "report.json").write_text(json.dumps({
        "lesson": lesson.id, "title": lesson.title, "module": lesson.pipeline.name, "dataset": run.dataset,
        "options": _jsonable(run.options), "seed": run.seed, "error": run.error,
        "steps": [r.to_json() for r in run.records]}, indent=2), encoding="utf-8")
    index = out / "index.html"
    index.write_text(_page(lesson, run, pictures, scene_note), encoding="utf-8")
    return index


def _write_pictures(session: Session, folder: Path) -> list[tuple[str, str]]:
    """PNGs of the images (with 2D overlays) and plots in the state: ``[(caption, relative path)]``."""
    import cv2

    from lab.viewer.renderers import curve_image, overlay_view, overlays_of

    written: list[tuple[str, str]] = []

    def save(caption: str, rgb: np.ndarray) -> None:
        filename = "".join(c if c.isalnum() or c in "-_" else "_" for c in caption) + ".png"
        cv2.imwrite(str(folder / filename), cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
        written.append((caption, f"images/{filename}"))

    for name, value in sorted(session.state.items()):
        overlays = [o for _, o in overlays_of(session.state, name)]
        if isinstance(value, Image):
            save(name, overlay_view(value, overlays))
        elif isinstance(value, ImageSet):
            for view in range(min(len(value), VIEWS_SHOWN)):
                save(f"{name} {value.names[view]}", overlay_view(value[view], overlays, view=view))
        elif isinstance(value, Curve):
            save(name, curve_image(value))
    return written


def _write_scene(session: Session, out: Path) -> str:
    """Save the 3D scene (``scene.html``) and its poster (``scene.png``); returns "" or why they could not be
    saved."""
    try:
        import cv2

        from lab.viewer.export import export_scene

        saved = export_scene(session)
        (out / "scene.html").write_text(saved.html, encoding="utf-8")
        cv2.imwrite(str(out / SCENE_POSTER), cv2.cvtColor(saved.poster, cv2.COLOR_RGB2BGR))
        return ""
    except Exception as exc:  # the report still has its tables and images
        return f"the 3D scene could not be saved ({type(exc).__name__}: {exc})"


#: The report's poster of the 3D scene.
SCENE_POSTER = "scene.png"
#: How long after the interactive scene's page has loaded the poster still covers it (ms): the page then
#: decodes and draws the scene, which a parent page cannot see (a file:// frame is another origin).
SCENE_REVEAL_MS = 4000
#: The script that loads the interactive scene under the poster when asked, and then shows it.
_SCENE_SCRIPT = """<script>
document.getElementById("scene-load").addEventListener("click", function () {
  var box = document.getElementById("scene"), note = document.getElementById("scene-note");
  var frame = document.createElement("iframe");
  frame.src = "scene.html"; frame.title = "3D scene (interactive)";
  note.textContent = "Loading the 3D scene\u2026 (the picture stays until it is ready; in software rendering "
    + "this takes a while)";
  this.remove();
  frame.addEventListener("load", function () {
    setTimeout(function () { box.classList.add("loaded"); note.textContent = "Interactive 3D scene: drag to "
      + "orbit, scroll to zoom."; }, REVEAL_MS);
  });
  box.appendChild(frame);
});
</script>"""


def _scene_section(scene_note: str) -> str:
    """The report's 3D scene: the poster at once, the interactive scene in its place when asked."""
    if scene_note:
        return f'<p class="error">{html.escape(scene_note)}</p>'
    return (f'<div id="scene" class="scene"><img src="{SCENE_POSTER}" alt="The 3D scene (a picture of it)">'
            '</div><p><button id="scene-load" type="button">Explore the 3D scene</button> '
            '<span id="scene-note">A picture of the 3D scene, as the interactive one starts.</span> '
            '<a href="scene.html">Open the 3D scene on its own page</a></p>'
            + _SCENE_SCRIPT.replace("REVEAL_MS", str(SCENE_REVEAL_MS)))


def _markdown(text: str) -> str:
    try:
        from markdown_it import MarkdownIt

        return MarkdownIt("commonmark", {"html": False}).render(text)
    except ImportError:  # pragma: no cover - markdown-it-py comes with typer's rich
        return f"<pre>{html.escape(text)}</pre>"


def _format(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, list):
        return "[" + ", ".join(_format(v) for v in value[:12]) + (", ..." if len(value) > 12 else "") + "]"
    return str(value)


def _page(lesson: Lesson, run: LessonRun, pictures: list[tuple[str, str]], scene_note: str) -> str:
    e = html.escape
    rows = []
    for record in run.records:
        metrics = "<br>".join(f"{e(k)} = {e(_format(v))}" for k, v in record.metrics.items())
        params = ", ".join(f"{k}={v!r}" for k, v in record.params.items())
        rows.append(f"<tr><td>{e(record.step)}</td><td>{e(params)}</td><td>{record.seconds:.3f}</td>"
                    f"<td>{metrics}</td></tr>")
    figures = "\n".join(f'<figure><img src="{e(src)}" alt="{e(caption)}">'
                        f'<figcaption>{e(caption)}</figcaption>'
                        f"</figure>" for caption, src in pictures)
    scene = _scene_section(scene_note)
    error = f'<p class="error">{e(run.error)}</p>' if run.error else ""
    options = ", ".join(f"{k}={v!r}" for k, v in run.options.items())
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{e(lesson.title)}: report</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 2rem auto; max-width: 1100px; padding: 0 1rem; }}
table {{ border-collapse: collapse; width: 100%; }} td, th {{ border: 1px solid #ccc; padding: .3rem .5rem;
vertical-align: top; font-size: .9rem; }} figure {{ display: inline-block; margin: .5rem; }}
figure img {{ max-width: 320px; }}
.scene {{ position: relative; width: 100%; aspect-ratio: 16 / 10; border: 1px solid #ccc; }}
.scene img, .scene iframe {{ position: absolute; inset: 0; width: 100%; height: 100%; border: 0; }}
.scene iframe {{ opacity: 0; }} .scene.loaded iframe {{ opacity: 1; }} .scene.loaded img {{ display: none; }}
.error {{ color: #b00; }} pre {{ background: #f6f6f6; padding: .5rem; overflow-x: auto; }}
</style></head><body>
<h1>{e(lesson.title)}</h1>
<p>Reference run of module <code>{e(lesson.pipeline.name)}</code> on dataset <code>{e(run.dataset)}</code>
({e(options)}), seed {run.seed}, headless.</p>
{error}
<h2>Steps and metrics</h2>
<table><tr><th>step</th><th>controls</th><th>seconds</th><th>metrics</th></tr>
{''.join(rows)}
</table>
<h2>Images</h2>
{figures or '<p>No images.</p>'}
<h2>3D scene</h2>
{scene}
<h2>The lesson</h2>
<details><summary>lesson.md</summary>
{_markdown(lesson.text)}
</details>
</body></html>
"""


__all__ = ["LessonRun", "run_lesson", "write_report"]
