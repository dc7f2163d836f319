"""The MLflow UI as a person looks at it: a real `mlflow server` on 127.0.0.1 over the finished micro pipeline's
store, headless Chromium doing the clicks of docs/monitoring.md's "Compare the models in MLflow"
(scripts/mlflow_screenshot.py, which also makes the screenshot of docs/monitoring.md). The model runs, their headline metric
columns (with the values of reports/task1/metrics.json) and the champion (reports/task1/champion.json: the tag
``pidc.role`` and the registered model's alias) must be on the page. The screenshots stay as CI artifacts:
reports/ci/mlflow-ui.png and reports/ci/mlflow-registry.png.
"""

from __future__ import annotations

import importlib.util
import json
import math
import re

import pytest
import yaml

from components.core.config import PROJECT_ROOT
from scripts.mlflow_screenshot import (
    ROLE_TAG,
    Look,
    compare_models,
    find_chromium,
    mlflow_server,
    registered_model_page,
)

ARTIFACTS = PROJECT_ROOT / "reports" / "ci"


def _browser() -> str:
    if importlib.util.find_spec("playwright") is None:
        pytest.fail("the Python package playwright is missing: pip install -e '.[test]' (scripts/setup.sh does)")
    try:
        return find_chromium()
    except FileNotFoundError as e:
        pytest.fail(str(e))


def _parents(project, experiment: str) -> dict[str, str | None]:
    """Run name → its parent run's name (``mlflow.parentRunId``), from the store: the UI nests each run under it."""
    import mlflow

    client = mlflow.MlflowClient(f"sqlite:///{project / 'mlflow.db'}")
    runs = client.search_runs([client.get_experiment_by_name(experiment).experiment_id], max_results=1000)
    names = {r.info.run_id: r.info.run_name for r in runs}
    return {r.info.run_name: names.get(r.data.tags.get("mlflow.parentRunId")) for r in runs}


@pytest.mark.slow
def test_the_models_their_headline_metrics_and_the_champion_show_in_the_mlflow_ui(micro_project):
    browser = _browser()
    metrics = json.loads((micro_project / "reports" / "task1" / "metrics.json").read_text())  # {model: {metric: value}}
    pointer = json.loads((micro_project / "reports" / "task1" / "champion.json").read_text())
    params = yaml.safe_load((micro_project / "params.yaml").read_text())
    champion, models = pointer["model"], list(metrics)
    # the headline figures the champion is chosen on (champion.json), as the model runs log them: task1.<name>
    headline = [k for k, v in pointer["metrics"].items() if not isinstance(v, bool)]
    shot, registry_shot = ARTIFACTS / "mlflow-ui.png", ARTIFACTS / "mlflow-registry.png"
    for f in (shot, registry_shot):
        f.unlink(missing_ok=True)

    with mlflow_server(f"sqlite:///{micro_project / 'mlflow.db'}") as url:
        look = compare_models(
            url, params["train"]["experiment"], shot, metrics=[f"task1.{k}" for k in headline], browser=browser
        )
        registry = registered_model_page(url, params["export"]["registered_model"], registry_shot, browser=browser)

    assert shot.is_file() and registry_shot.is_file()
    assert not look.missing_columns, f"the Columns menu does not offer {look.missing_columns}\n{look.describe()}"
    hidden = [m for m in models if look.row(m) is None]
    assert not hidden, (
        f"model runs not in the table after expanding the grid run: {hidden}; the runs' parents in the store: "
        f"{_parents(micro_project, params['train']['experiment'])}\n{look.describe()}"
    )
    for model in models:
        row = look.row(model)
        for name in headline:
            column = Look.metric(f"task1.{name}")
            assert column in row, f"{model}: column {column} not rendered (off screen?)\n{look.describe()}"
            expected = float(metrics[model][name])
            shown = row[column]
            # logged to 6 significant digits (flows/tracking.py), so within half a unit of the 6th digit
            assert shown not in ("", "-") and math.isclose(float(shown), expected, rel_tol=5e-6, abs_tol=1e-9), (
                f"{model}: {column} shows {shown!r}, reports/task1/metrics.json has {expected}\n{look.describe()}"
            )
    roles = {m: look.row(m).get(Look.tag(ROLE_TAG)) for m in models}
    assert roles[champion] == "champion", f"the champion {champion}'s {ROLE_TAG}: {roles}\n{look.describe()}"
    assert [m for m, r in roles.items() if r == "champion"] == [champion], roles

    # the registered model: one version per model, the alias @champion on the champion's
    with_alias = [r["text"] for r in registry.rows if "@ champion" in r["text"]]
    named = re.compile(rf"(?<![\w-]){re.escape(champion)}(?![\w-])")  # cues-24, not cues-24-ensemble
    assert len(with_alias) == 1 and named.search(with_alias[0]), (
        f"the @champion alias should mark {champion}'s version; versions shown:\n"
        + "\n".join(r["text"] for r in registry.rows)
        + f"\npage text:\n{registry.text[:3000]}"
    )
