"""Packaging: README's set-up commands, .ci/run, pyproject and the Dockerfile agree with each other and
with the CLI they name."""

from __future__ import annotations

import re
import shlex
import subprocess
import tomllib
from pathlib import Path

import pytest
import typer.main

from lab.cli import app

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
CI_RUN = ROOT / ".ci" / "run"


def code_block_after(heading: str) -> list[str]:
    """The command lines of the first fenced ``sh`` block after the paragraph containing ``heading``."""
    match = re.search(re.escape(heading) + r".*?```sh\n(.*?)\n```", README, flags=re.DOTALL)
    assert match, f"README.md has no sh block after {heading!r}"
    return [line for line in match.group(1).splitlines() if line.strip() and not line.startswith("#")]


def test_readme_test_command_is_what_ci_runs():
    (command,) = code_block_after("**Run every test**")
    assert "apt-get install -y chromium" in command
    assert command.endswith("pytest")
    ci_lines = [line.strip() for line in CI_RUN.read_text().splitlines()]
    assert command in ci_lines, f"{CI_RUN} does not run the README's test command {command!r}"


def test_pip_installs_into_the_python_that_runs_pytest():
    (command,) = code_block_after("**Run every test**")
    pip = re.search(r"(\S+) -m pip install -e \"\.\[test\]\"", command)
    pytest_run = re.search(r"(\S+) -m pytest$", command)
    assert pip and pytest_run and pip.group(1) == pytest_run.group(1)


def test_ci_script_is_strict_bash_that_needs_no_stdin():
    text = CI_RUN.read_text()
    assert text.startswith("#!/usr/bin/env bash\n")
    assert "set -euo pipefail" in text
    assert "DEBIAN_FRONTEND=noninteractive" in text
    subprocess.run(["bash", "-n", str(CI_RUN)], check=True, timeout=30)


def test_readme_start_command_installs_then_serves():
    (command,) = code_block_after("**Start the lab**")
    install, serve = command.split(" && ")
    assert install == "python3 -m pip install -e ."
    assert serve == "vision-lab serve"
    assert "http://127.0.0.1:8000/" in README and "http://127.0.0.1:8080/" in README


def test_readme_urls_are_the_serve_defaults():
    serve = typer.main.get_command(app).commands["serve"]
    defaults = {p.name: p.default for p in serve.params}
    assert defaults == {"host": "127.0.0.1", "port": 8000, "viewer_port": 8080, "data_root": None,
                        "unsafe_sandbox": False,  # the sandbox is on unless the operator says otherwise
                        "no_warmup": False,  # and the fast kernels compile ahead in the background
                        # one process that grades, as a lone server (README "Behind a proxy" for more)
                        "workers": 1, "worker_id": None, "peers": None, "no_grading": False,
                        "trust_forwarded_for": False}


def test_pyproject_pins_torch_and_names_the_console_script():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert "torch==2.13.0" in project["dependencies"]
    assert not [d for d in project["dependencies"] if d.startswith("torch") and d != "torch==2.13.0"]
    assert project["scripts"] == {"vision-lab": "lab.cli:app"}
    test_extras = " ".join(project["optional-dependencies"]["test"])
    assert "pytest" in test_extras and "playwright" in test_extras


def test_dockerfile_is_a_cpu_image_of_the_pinned_torch():
    text = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^FROM python:3\.11-slim$", text, flags=re.MULTILINE)
    torch_line = next(line for line in text.splitlines() if "torch==" in line and not line.startswith("#"))
    assert "--index-url https://download.pytorch.org/whl/cpu" in torch_line and "torch==2.13.0" in torch_line
    assert text.index(torch_line) < text.index("pip install -e .")  # CPU torch before the project
    assert re.search(r"^EXPOSE 8000 8080$", text, flags=re.MULTILINE)
    assert 'CMD ["vision-lab", "serve", "--host", "0.0.0.0"]' in text
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert ".git" in ignored and "venv" in ignored


def _readme_cli_examples() -> list[list[str]]:
    examples = []
    for block in re.findall(r"```sh\n(.*?)\n```", README, flags=re.DOTALL):
        for line in block.splitlines():
            line = line.split("  #")[0].strip()
            if line.startswith("vision-lab ") and "&&" not in line:
                examples.append(shlex.split(line)[1:])
    return examples


@pytest.mark.parametrize("args", _readme_cli_examples(), ids=lambda a: " ".join(a))
def test_readme_cli_examples_parse(args):
    """Every ``vision-lab ...`` example in the README names a real command and real options."""
    group = typer.main.get_command(app)
    name, *rest = args
    command = group.commands.get(name)
    assert command is not None, f"README uses an unknown command {name!r}"
    command.make_context(name, list(rest), resilient_parsing=False)  # raises on an unknown option


def test_readme_has_cli_examples_for_every_command():
    used = {args[0] for args in _readme_cli_examples()}
    assert used == set(typer.main.get_command(app).commands)


def test_readme_cli_examples_use_real_steps_controls_and_options():
    """``--set STEP.CONTROL=VALUE`` and ``--option KEY=VALUE`` in the README exist in the module they name."""
    import lab
    from lab.cli import parse_options, parse_settings
    from lab.modules import get_pipeline

    group = typer.main.get_command(app)
    checked = 0
    for args in _readme_cli_examples():
        if args[0] not in ("run", "export"):
            continue
        ctx = group.commands[args[0]].make_context(args[0], list(args[1:]))
        pipeline = get_pipeline(ctx.params["module"])
        parse_settings(pipeline, ctx.params["set_"])  # raises for an unknown step/control or a bad value
        dataset = ctx.params["dataset"]
        if dataset is not None and dataset not in [d.name for d in pipeline.datasets]:
            dataset = next(d.name for d in pipeline.datasets if d.takes_path)
        option_names = {o.name for o in pipeline.dataset(dataset).options}
        assert set(parse_options(ctx.params["option"])) <= option_names, args
        what = ctx.params.get("what")
        if what:
            assert what in {name for spec in pipeline.steps for name in spec.writes}, what
        checked += 1
    assert checked >= 5
    assert lab.open_session  # the Python API the README shows


def test_readme_python_example_runs():
    """The README's Python block runs as written (the folder is OpenCV's sample photos here)."""
    block = re.search(r"```python\n(.*?)\n```", README, flags=re.DOTALL).group(1)
    samples = ROOT.parent / "shared" / "data" / "opencv-samples"
    assert '"path/to/photos"' in block
    namespace: dict = {}
    exec(compile(block.replace('"path/to/photos"', repr(str(samples))), "README.md", "exec"), namespace)
    assert namespace["session"].metrics["refine_calibration"]["rms_px"] < 0.5
    assert namespace["photos"].dataset == "folder"


def test_readme_rest_endpoints_exist():
    from lab.api.app import create_app
    from lab.core.store import SessionStore

    def shape(path: str) -> str:
        return re.sub(r"\{[^}]*\}", "{}", path.split("?")[0])

    served = {(method.upper(), shape(path))
              for path, operations in create_app(SessionStore()).openapi()["paths"].items() for method in operations}
    listed = set()
    for row in re.findall(r"^\| (`(?:GET|POST|PUT|DELETE) .*?) \|", README, flags=re.MULTILINE):
        for method, path in re.findall(r"`(GET|POST|PUT|DELETE) (/api/[^`]*)`", row):
            listed.add((method, shape(path)))
    assert len(listed) >= 10
    assert listed <= served, sorted(listed - served)
