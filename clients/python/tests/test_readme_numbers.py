"""The README's table of the bundled policies is written from results/*/evaluation.json (what
`prac evaluate` wrote) by scripts/readme-numbers: it must say what those files say."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import pathlib
import types

ROOT = pathlib.Path(__file__).resolve().parents[3]


def readme_numbers() -> types.ModuleType:
    path = ROOT / "scripts" / "readme-numbers"
    loader = importlib.machinery.SourceFileLoader("readme_numbers", str(path))
    spec = importlib.util.spec_from_loader("readme_numbers", loader)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def test_the_readme_bundle_table_is_what_the_evaluations_say() -> None:
    module = readme_numbers()
    text = (ROOT / "README.md").read_text()
    assert module.rewritten(text) == text, "run scripts/readme-numbers"


def test_a_changed_number_in_the_table_is_caught() -> None:
    module = readme_numbers()
    text = (ROOT / "README.md").read_text()
    table = text[text.index(module.BEGIN) : text.index(module.END)]
    assert "| `hopper` |" in table
    tampered = text.replace("| `hopper` | ", "| `hopper` | 1", 1)
    assert module.rewritten(tampered) != tampered
    assert module.rewritten(tampered) == text
