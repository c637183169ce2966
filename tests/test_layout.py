"""The package's shape: only `legslam.cli` parses arguments or prints (the library reports
through the "legslam" logger), and every package says what lives in it."""

import ast
from pathlib import Path

import legslam

PACKAGE = Path(legslam.__file__).parent


def _modules():
    return sorted(p for p in PACKAGE.rglob("*.py") if "cli" not in p.relative_to(PACKAGE).parts)


def test_only_the_cli_parses_arguments_or_prints():
    offenders = []
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text())):
            imported = ([a.name for a in node.names] if isinstance(node, ast.Import)
                        else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(name.split(".")[0] == "argparse" for name in imported):
                offenders.append(f"{path.relative_to(PACKAGE)}:{node.lineno} imports argparse")
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "print":
                offenders.append(f"{path.relative_to(PACKAGE)}:{node.lineno} prints")
    assert len(_modules()) > 20 and not offenders, offenders


def test_every_package_says_what_lives_in_it():
    for init in PACKAGE.rglob("__init__.py"):
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc and len(doc) > 60, f"{init.relative_to(PACKAGE)} has no docstring to speak of"
