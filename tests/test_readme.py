"""The README's "Using it" example runs as written."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_the_readme_search_example_runs_as_written(capsys):
    text = README.read_text()
    section = text[text.index("## Using it"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert "Simulator(diagram)" in code and "set_initial_conditions" in code
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    out = capsys.readouterr().out
    assert "requested termination" in out and "search ended: success" in out
    history = namespace["history"]
    assert history and history[-1].action.kind == "grasp" and history[-1].success
    assert history[-1].action.grasp.object_id == namespace["controller"].target_id
