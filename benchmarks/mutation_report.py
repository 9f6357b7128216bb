"""The survivors of ``make mutate`` as a Markdown table (docs/results/mutation.md).

Reads mutmut's results in ``mutants/`` (run from the repository root after ``mutmut run``) and
prints, per mutated function, how many mutants were killed and, for every mutant that was not,
its status and the changed line(s). Only the mutants of the given name patterns (the ones
``make mutate`` ran) are counted.

    python benchmarks/mutation_report.py 'cutterpose.budget.*' ... > /tmp/survivors.md
"""

from __future__ import annotations

import fnmatch
import sys
from collections import Counter, defaultdict
from difflib import unified_diff


def _functions(path) -> dict:
    """name -> source of every function in mutmut's copy of ``path`` (the original as
    ``<f>__mutmut_orig``, each mutant as ``<f>__mutmut_<n>``); parsed with ``ast`` (the file
    holds every mutant: libcst would take minutes)."""
    import ast
    from pathlib import Path

    text = (Path("mutants") / path).read_text()
    lines = text.splitlines()
    return {node.name: "\n".join(lines[node.lineno - 1:node.end_lineno])
            for node in ast.walk(ast.parse(text))
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)}


def _diff(functions: dict, name: str) -> str:
    local = name.rsplit(".", 1)[-1]
    orig = functions.get(local.rsplit("__mutmut_", 1)[0] + "__mutmut_orig", "")
    lines = [ln for ln in (orig.splitlines(), functions.get(local, "").splitlines())]
    # the mutant's own name differs from the original's on the def line: compare without it,
    # but keep the signature (a mutated default shows there)
    sig = [ln.replace(local, "") for ln in lines[1][:1]]
    orig_sig = [ln.replace(local.rsplit("__mutmut_", 1)[0] + "__mutmut_orig", "")
                for ln in lines[0][:1]]
    return "\n".join(unified_diff(orig_sig + lines[0][1:], sig + lines[1][1:], lineterm=""))


def _changed_lines(diff: str) -> str:
    minus = [ln[1:].strip() for ln in diff.splitlines()
             if ln.startswith("-") and not ln.startswith("---")]
    plus = [ln[1:].strip() for ln in diff.splitlines()
            if ln.startswith("+") and not ln.startswith("+++")]
    return f"`{' / '.join(minus)[:110]}` → `{' / '.join(plus)[:110]}`".replace("|", "\\|")


def main(patterns: list[str]) -> int:
    from mutmut.mutation.data import SourceFileMutationData
    from mutmut.stats import status_by_exit_code
    from mutmut.utils.file_utils import walk_mutatable_files

    counts: dict = defaultdict(Counter)
    rows = []
    for path in walk_mutatable_files():
        data = SourceFileMutationData(path=path)
        data.load()
        functions = None
        for name, code in sorted(data.exit_code_by_key.items()):
            if patterns and not any(fnmatch.fnmatch(name, p) for p in patterns):
                continue
            status = status_by_exit_code[code]
            func = name.rsplit("__mutmut_", 1)[0]
            counts[func][status] += 1
            if status not in ("killed", "caught by type check"):
                functions = functions or _functions(path)      # parsed once per file
                rows.append((name, status, _changed_lines(_diff(functions, name))))
    print("| function | mutants | killed | other |")
    print("| --- | ---: | ---: | --- |")
    for func, c in sorted(counts.items()):
        other = ", ".join(f"{k} {v}" for k, v in c.items() if k != "killed")
        print(f"| `{func}` | {sum(c.values())} | {c['killed']} | {other} |")
    print()
    print("| mutant | status | change |")
    print("| --- | --- | --- |")
    for name, status, change in rows:
        print(f"| `{name}` | {status} | {change} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
