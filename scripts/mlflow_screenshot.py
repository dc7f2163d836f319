"""Look at the models in the MLflow UI as a person would: headless Chromium, the clicks of docs/monitoring.md's "Compare the
models in MLflow", a screenshot, and the runs table read back from the page.

    python scripts/mlflow_screenshot.py --size 1920x720 --out docs/mlflow-models.png  # over ./mlflow.db
    python scripts/mlflow_screenshot.py --store sqlite:////path/to/mlflow.db --out shot.png
    python scripts/mlflow_screenshot.py --url http://127.0.0.1:5000 --out shot.png   # a server already running
    python scripts/mlflow_screenshot.py --registry-out docs/mlflow-registry.png ...    # also the registered model

Without ``--url`` it starts ``mlflow server`` on 127.0.0.1 (a free port) over ``--store`` and stops it at the end.
The browser is the system's Chromium (Debian's ``chromium``, or ``$PIDC_CHROMIUM``) driven by Playwright, which
downloads no browser of its own. The clicks (:func:`compare_models`), from the experiments list:

1. click the experiment (MLflow 3.17 opens it in its GenAI overview) and dismiss the first-visit hint;
2. switch the toggle at the top left to **Model training**: the runs table;
3. close the MLflow Assistant panel, which opens on a first visit;
4. expand the newest grid run (``grid-<hash>``): the model runs are nested under it;
5. **Columns** → untick Dataset and Source (the same for every model), then search and tick each headline metric and
   the tag ``pidc.role`` (champion / challenger / candidate);
6. widen the run names' and those columns to their content (drag the edge of the column header); the screenshot.

And for the registered model (:func:`registered_model_page`): **Model training** → **Model registry** → ``pidc``: its
versions, one per model (version tag and description name the model), the aliases ``@champion`` and ``@challenger``
on theirs.

Used by ``tests/test_mlflow_ui.py`` (on the micro pipeline's store) and for ``docs/mlflow-models.png`` (docs/monitoring.md).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

#: the Task I headline metrics each model run logs (flows/tracking.py: ``task1.<metric>``)
HEADLINE_METRICS = ("task1.test_nll", "task1.calibration_error", "task1.calibration_band", "task1.info_gain_nats")
#: the run tag that names the champion and the challenger (flows/tracking.py ``set_champion_alias``)
ROLE_TAG = "pidc.role"
RUN_NAME = "attributes.`Run Name`"  # the column ids of the runs table: attributes.`X`, metrics.`X`, tags.`X`
#: default columns of the runs table that the comparison does without (one data set for all; runs have no source)
HIDDEN_COLUMNS = ("Dataset", "Source")
BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
SIZE = (1920, 1080)  # the browser window: the comparison's columns fit without scrolling
TIMEOUT_MS = 60_000  # the UI on a loaded 2-core machine: a first page load takes seconds


def find_chromium() -> str:
    """The Chromium executable: ``$PIDC_CHROMIUM``, else the first of ``chromium`` (Debian), ``chromium-browser``,
    ``google-chrome`` on PATH."""
    if os.environ.get("PIDC_CHROMIUM"):
        return os.environ["PIDC_CHROMIUM"]
    for name in BROWSERS:
        if found := shutil.which(name):
            return found
    raise FileNotFoundError(
        "no Chromium found (looked for $PIDC_CHROMIUM, then " + ", ".join(BROWSERS) + " on PATH): install it with "
        "`apt-get install chromium` (scripts/setup.sh does when apt-get is there) or point PIDC_CHROMIUM at one"
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def mlflow_server(store: str, timeout: float = 180) -> Iterator[str]:
    """A real ``mlflow server`` over the tracking store ``store`` (e.g. ``sqlite:////abs/mlflow.db``) on 127.0.0.1
    and a free port, healthy (``/health``) before it yields its URL; stopped (its whole process group) afterwards.
    It runs in a temporary folder so that it writes nothing beside the store; its log is in the error raised when
    it does not start."""
    port = _free_port()
    workdir = Path(tempfile.mkdtemp(prefix="pidc-mlflow-server-"))
    log_path = workdir / "server.log"
    env = dict(os.environ, MLFLOW_DISABLE_TELEMETRY="true", DO_NOT_TRACK="1")
    cmd = [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", store]
    cmd += ["--host", "127.0.0.1", "--port", str(port), "--workers", "1"]
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(cmd, cwd=workdir, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + timeout
        while True:
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(
                    f"`mlflow server` over {store} did not become healthy within {timeout:.0f} s "
                    f"(exit code {proc.poll()}); its log:\n{log_path.read_text(errors='replace')[-4000:]}"
                )
            time.sleep(0.5)
        yield url
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, 15)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, 9)
            proc.wait(timeout=10)
        shutil.rmtree(workdir, ignore_errors=True)


@dataclass
class Look:
    """What the page showed after the clicks: its URL, its text, the runs table as rendered (one dict per row:
    column id → cell text; the column ids are MLflow's, e.g. ``metrics.`task1.test_nll```, ``tags.`pidc.role```,
    ``attributes.`Run Name```), the columns asked for but absent from the Columns menu, and the screenshot."""

    url: str
    text: str
    rows: list[dict[str, str]]
    headers: list[str]
    missing_columns: list[str] = field(default_factory=list)
    screenshot: Path | None = None

    @staticmethod
    def metric(name: str) -> str:
        return f"metrics.`{name}`"

    @staticmethod
    def tag(name: str) -> str:
        return f"tags.`{name}`"

    @staticmethod
    def run_name(row: dict[str, str]) -> str:
        """A row's run name: the last line of its Run Name cell (the first is the run's color)."""
        cell = row.get(RUN_NAME, "").strip()
        return cell.splitlines()[-1].strip() if cell else ""

    def run_names(self) -> list[str]:
        """The run names in the table, top to bottom."""
        return [name for row in self.rows if (name := self.run_name(row))]

    def row(self, run_name: str) -> dict[str, str] | None:
        """The table row of run ``run_name`` (None when not shown)."""
        return next((row for row in self.rows if self.run_name(row) == run_name), None)

    def describe(self) -> str:
        """The table and page text, for a failing assertion."""
        lines = [f"page {self.url}", f"columns rendered: {self.headers}"]
        if self.missing_columns:
            lines.append(f"columns not offered by the Columns menu: {self.missing_columns}")
        lines += [f"row: {r}" for r in self.rows]
        lines.append("page text:\n" + self.text[:6000])
        return "\n".join(lines)


# the rendered runs table (ag-grid): rows are split across the pinned and scrolling containers, joined by row-index
_READ_TABLE = """() => {
  const rows = {};
  for (const row of document.querySelectorAll('.ag-row')) {
    const i = Number(row.getAttribute('row-index'));
    rows[i] = rows[i] || {};
    for (const cell of row.querySelectorAll('[col-id]')) rows[i][cell.getAttribute('col-id')] = cell.innerText.trim();
  }
  const headers = [...document.querySelectorAll('.ag-header-cell[col-id]')].map(c => c.getAttribute('col-id'));
  return {rows: Object.keys(rows).sort((a, b) => a - b).map(k => rows[k]), headers};
}"""


class UIError(RuntimeError):
    """A step of the clicks failed: the message says which, with the page's address and text."""

    def __init__(self, message: str, page) -> None:
        try:
            text = page.inner_text("body", timeout=5_000)
        except Exception:  # the page is gone
            text = "(not readable)"
        super().__init__(f"{message}\npage {page.url}; its text:\n{text[:4000]}")


def _click_if_shown(locator, timeout_ms: int) -> bool:
    """Click ``locator`` if it shows up within ``timeout_ms`` (a hint or panel that may or may not open; 0: if it is
    there now)."""
    if timeout_ms <= 0:  # (Playwright reads a timeout of 0 as "wait for ever")
        if not locator.first.is_visible():
            return False
        locator.first.click()
        return True
    try:
        locator.first.wait_for(state="visible", timeout=timeout_ms)
    except Exception:  # playwright's TimeoutError: it did not show up
        return False
    locator.first.click()
    return True


def _click(page, target, timeout_s: float = TIMEOUT_MS / 1000) -> None:
    """Click ``target``; a first-visit hint that shows up over it (MLflow's "Detect Issues" hint: *Got it*, the new
    Model Registry UI announcement: *Try it now*) is dismissed first, as a person would, whenever it comes."""
    hints = [page.get_by_role("button", name="Got it"), page.get_by_text("Try it now", exact=True)]
    deadline = time.monotonic() + timeout_s
    while True:
        for hint in hints:
            if hint.first.is_visible():
                hint.first.click()
        try:
            target.first.click(timeout=3_000)
            return
        except Exception as e:  # playwright's TimeoutError: not there yet, or covered by a hint
            if time.monotonic() > deadline:
                raise UIError(f"could not click {target} within {timeout_s:.0f} s ({e})", page) from None


def _show_runs(page, experiment: str, timeout_s: float = 2 * TIMEOUT_MS / 1000) -> None:
    """From the experiments list to ``experiment``'s runs table: click the experiment while the page is not on it,
    the workflow toggle → *Model training* once it is, until the table says how many runs match. On a loaded machine
    a click can land before the page has wired its target and be lost: CI on 2026-11-26 lost the toggle's click, CI
    on 7e41536 the experiment's (the page stayed on the list while the toggle was clicked again and again). So each
    20 s the count does not show, the page's address decides the next click again, up to ``timeout_s``."""
    count = page.get_by_text(re.compile(r"\d+ matching runs?")).first
    deadline = time.monotonic() + timeout_s
    while True:
        if re.search(r"#/experiments/\d+", page.url):
            _click(page, page.get_by_text("Model training", exact=True))
        else:
            _click(page, page.get_by_role("link", name=experiment, exact=True))
            try:
                page.wait_for_url(re.compile(r"#/experiments/\d+"), timeout=10_000)
            except Exception:  # playwright's TimeoutError: the click was lost; the next round clicks it again
                pass
            _click_if_shown(page.get_by_role("button", name="Got it"), 5_000)
            if re.search(r"#/experiments/\d+", page.url):
                _click(page, page.get_by_text("Model training", exact=True))
        try:
            count.wait_for(state="visible", timeout=20_000)
            return
        except Exception as e:  # playwright's TimeoutError
            if time.monotonic() > deadline:
                raise UIError(
                    f"no runs table ('N matching runs') for experiment {experiment!r} within {timeout_s:.0f} s of "
                    f"clicks ({e})",
                    page,
                ) from None


def _set_column(page, name: str, shown: bool = True, timeout_s: float = 30) -> bool:
    """Columns → type ``name`` into the search → tick it (``shown``) or untick it; False when the menu has not offered
    it within ``timeout_s`` (the menu lists the metrics and tags of the runs loaded so far: it is tried again until
    then)."""
    deadline = time.monotonic() + timeout_s
    while True:
        page.get_by_role("button", name="Columns", exact=True).click()
        search = page.get_by_placeholder("Search columns")
        try:
            search.wait_for(state="visible", timeout=5_000)
            search.fill(name)
            item = page.get_by_test_id("column-selector-tree").get_by_text(name, exact=True).first
            item.wait_for(state="visible", timeout=3_000)
        except Exception:  # playwright's TimeoutError: the menu did not open, or does not offer the column (yet)
            page.keyboard.press("Escape")
            if time.monotonic() > deadline:
                return False
            page.wait_for_timeout(1_000)
            continue
        ticked = item.evaluate("e => /checkbox-checked/.test(e.closest('[class*=\"treenode\"]')?.className ?? '')")
        if ticked != shown:
            item.click()
        page.keyboard.press("Escape")
        return True


_OVERFLOW = """id => Math.max(0, ...[...document.querySelectorAll('[col-id]')]
  .filter(c => c.getAttribute('col-id') === id)
  .flatMap(c => [c, ...c.querySelectorAll('*')])
  .map(x => x.scrollWidth - x.clientWidth))"""


def _widen(page, column_id: str) -> None:
    """Drag the right edge of a column's header until its name and values show whole (as a person would)."""
    header = page.locator(f'.ag-header-cell[col-id="{column_id}"]').first
    try:
        header.wait_for(state="visible", timeout=10_000)
    except Exception:  # not rendered (off screen): nothing to widen
        return
    missing = page.evaluate(_OVERFLOW, column_id)
    handle = header.locator(".ag-header-cell-resize").first
    box = handle.bounding_box() if missing > 0 and handle.count() else None
    if box is None:
        return
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    handle.hover()
    page.mouse.down()
    for i in range(1, 11):
        page.mouse.move(x + (missing + 12) * i / 10, y)
    page.mouse.up()


@contextlib.contextmanager
def _page(browser: str | None, size: tuple[int, int]):
    """A fresh headless Chromium page (a first visit: no saved UI state), closed afterwards."""
    from playwright.sync_api import sync_playwright

    executable = browser or find_chromium()
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=executable, headless=True, args=["--disable-gpu"])
        try:
            page = chromium.new_page(viewport={"width": size[0], "height": size[1]})
            page.set_default_timeout(TIMEOUT_MS)
            yield page
        finally:
            chromium.close()


# the expander of a parent run's Run Name cell shows a plus (folded: its icon's first path draws a vertical stroke,
# an SVG "V" command) or a minus (unfolded: no "V")
_FOLDED = "b => /V/.test(b.querySelector('svg path')?.getAttribute('d') ?? '')"
_ROW_COUNT = "() => new Set([...document.querySelectorAll('.ag-row')].map(r => r.getAttribute('row-index'))).size"


def _expand(page, row, timeout_s: float = TIMEOUT_MS / 1000) -> None:
    """Unfold a parent run's ``row`` (its expander: the one button of its Run Name cell) until its child runs show.
    While the runs still load, the table may re-render and fold it again (once seen in CI: the click landed, the
    children never showed): the expander's state is read back, and it is clicked again until the children are rows."""
    button = row.locator(f'[col-id="{RUN_NAME}"]').get_by_role("button").first
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            button.wait_for(state="visible", timeout=5_000)
            if button.evaluate(_FOLDED):
                before = page.evaluate(_ROW_COUNT)
                _click(page, button)
                page.wait_for_function(f"n => ({_ROW_COUNT})() > n", arg=before, timeout=5_000)
            if not button.evaluate(_FOLDED):
                return
        except Exception as e:  # playwright's TimeoutError: not rendered yet, or the children did not show
            if time.monotonic() > deadline:
                raise UIError(f"could not unfold the run {row} within {timeout_s:.0f} s ({e})", page) from None
        page.wait_for_timeout(500)


def _close_assistant(page, timeout_ms: int = 3_000) -> None:
    """The MLflow Assistant panel opens on a first visit and covers the right third of the page: close it."""
    _click_if_shown(page.locator('[data-component-id="mlflow.assistant.chat_panel.close"]'), timeout_ms)


def _screenshot(page, out: Path | None) -> None:
    page.wait_for_timeout(1_000)  # let the last resize or render settle
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(out))


def compare_models(
    url: str,
    experiment: str,
    out: Path | None,
    metrics: Sequence[str] = HEADLINE_METRICS,
    tags: Sequence[str] = (ROLE_TAG,),
    hide: Sequence[str] = HIDDEN_COLUMNS,
    browser: str | None = None,
    size: tuple[int, int] = SIZE,
) -> Look:
    """Open ``url`` (an MLflow server) in headless Chromium, do docs/monitoring.md's clicks on ``experiment`` (see the module
    docstring), screenshot the page to ``out`` (when given) and return what it showed."""
    with _page(browser, size) as page:
        # 1. the experiments list → the experiment (its GenAI overview, with a "Detect Issues" hint on top)
        # 2. the workflow toggle → Model training: the runs table
        page.goto(f"{url}/#/experiments")
        _show_runs(page, experiment)
        # 3. the assistant panel
        _close_assistant(page)
        # 4. the newest grid run (runs are sorted newest first): its expander (the one button of its Run Name cell)
        grid_row = page.locator(".ag-row").filter(has=page.get_by_role("link", name=re.compile(r"^grid-"))).first
        _expand(page, grid_row)
        # 5. the columns: without Dataset and Source, with each headline metric and the role tag
        for name in hide:
            _set_column(page, name, shown=False, timeout_s=5)
        missing = [name for name in [*metrics, *tags] if not _set_column(page, name)]
        # 6. whole names and values, then the picture (the assistant panel again, should it have opened late)
        _close_assistant(page, timeout_ms=0)
        _expand(page, grid_row)  # (a no-op unless a re-render folded it again)
        for column in [RUN_NAME, *map(Look.metric, metrics), *map(Look.tag, tags)]:
            _widen(page, column)
        _screenshot(page, out)
        table = page.evaluate(_READ_TABLE)
        return Look(
            url=page.url,
            text=page.inner_text("body"),
            rows=table["rows"],
            headers=table["headers"],
            missing_columns=missing,
            screenshot=out,
        )


def registered_model_page(
    url: str, name: str, out: Path | None, browser: str | None = None, size: tuple[int, int] = SIZE
) -> Look:
    """Open ``url`` in headless Chromium, click **Model training** → **Model registry** → ``name`` (dismissing the
    announcement of the new Model Registry UI: *Try it now*), screenshot its versions to ``out`` (when given) and
    return them: ``rows`` one dict per version, ``{"text": the row's text}``, whitespace collapsed (e.g. ``Version 3
    … pidc.model: cnn-24 … @ champion …``)."""
    with _page(browser, size) as page:
        page.goto(f"{url}/#/experiments")
        _click(page, page.get_by_text("Model training", exact=True))  # the GenAI view's sidebar has no registry
        _click(page, page.get_by_role("link", name="Model registry"))
        _click(page, page.get_by_role("link", name=name, exact=True))
        _click_if_shown(page.get_by_text("Try it now", exact=True), 3_000)
        page.get_by_text(re.compile(r"^Version \d+$")).first.wait_for()
        _close_assistant(page)
        _screenshot(page, out)
        texts = [" ".join(row.inner_text().split()) for row in page.get_by_role("row").all()]
        return Look(
            url=page.url,
            text=page.inner_text("body"),
            rows=[{"text": t} for t in texts if re.match(r"Version \d+ ", t)],
            headers=[],
            screenshot=out,
        )


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    where = ap.add_mutually_exclusive_group()
    where.add_argument("--store", default="sqlite:///mlflow.db", help="tracking store to serve (default: %(default)s)")
    where.add_argument("--url", help="an MLflow server already running (then no store is served)")
    ap.add_argument("--experiment", default="pidc-grid", help="experiment name (default: %(default)s)")
    ap.add_argument(
        "--metric", action="append", help=f"a metric column (repeat; default: {' '.join(HEADLINE_METRICS)})"
    )
    ap.add_argument("--tag", action="append", help=f"a tag column (repeat; default: {ROLE_TAG})")
    ap.add_argument(
        "--out", type=Path, default=Path("reports/ci/mlflow-ui.png"), help="screenshot (default: %(default)s)"
    )
    ap.add_argument("--registry-out", type=Path, help="also screenshot the registered model's versions to this file")
    ap.add_argument("--registered-model", default="pidc", help="registered model name (default: %(default)s)")
    ap.add_argument("--size", default="x".join(map(str, SIZE)), help="browser window WxH (default: %(default)s)")
    args = ap.parse_args(argv)
    store = args.store
    if store.startswith("sqlite:///") and not store.startswith("sqlite:////"):  # relative: the server runs elsewhere
        store = f"sqlite:///{Path(store.removeprefix('sqlite:///')).resolve()}"
    width, height = (int(v) for v in args.size.lower().split("x"))
    with contextlib.ExitStack() as stack:
        url = args.url or stack.enter_context(mlflow_server(store))
        look = compare_models(
            url,
            args.experiment,
            args.out,
            metrics=args.metric or HEADLINE_METRICS,
            tags=args.tag or (ROLE_TAG,),
            size=(width, height),
        )
        print(f"{args.out}: {len(look.run_names())} runs shown: {', '.join(look.run_names())}")
        if look.missing_columns:
            print(f"not offered by the Columns menu (not logged?): {', '.join(look.missing_columns)}", file=sys.stderr)
        if args.registry_out:
            registry = registered_model_page(url, args.registered_model, args.registry_out, size=(width, height))
            print(f"{args.registry_out}: {len(registry.rows)} versions of {args.registered_model}")
    return 1 if look.missing_columns else 0


if __name__ == "__main__":
    sys.exit(main())
