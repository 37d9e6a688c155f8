"""The README is a front door that works as pasted.

Its fenced ``bash`` blocks hold only commands a reader can run: every ``usplat`` subcommand
answers ``--help`` and knows every ``--flag`` the README passes it, ``usplat train``'s
``section.key=value`` overrides name real config keys, every ``python`` script exists and
knows its flags, every ``bash scripts/run.sh X`` names one of the script's commands. The torch
snippet runs; the other Python snippets compile and their imports resolve. The README stays
under 250 lines, links from it and from ``docs/`` reach real files and headings, and no page
speaks of how the work was organised (issue numbers and the like).

One subprocess per distinct command, all started at once: about 10 s in all.
"""

import ast
import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MAX_LINES = 250
#: Words about the work's process rather than the project: an issue or stop number, or a
#: number after "#".
PROCESS_WORDS = re.compile(r"\bissue \d+|\bstop \d+|#\d{2}\b", re.IGNORECASE)
#: A command, its help and a snippet each finish in a few seconds; this only stops a hang.
TIMEOUT_S = 120


def fenced_blocks(text: str, lang: str) -> list[str]:
    """The bodies of the ```lang fenced blocks of a Markdown text.

    Examples:
        >>> fenced_blocks("a\\n```bash\\nls -l\\n```\\n```python\\nx = 1\\n```\\n", "bash")
        ['ls -l\\n']
    """
    return re.findall(rf"^```{lang}\n(.*?)^```", text, re.MULTILINE | re.DOTALL)


def commands(block: str) -> list[list[str]]:
    """The shell commands of a block, continuation lines joined and comments dropped.

    Examples:
        >>> commands("usplat eval --out a \\\\\\n    --data b   # note\\n# only a comment\\n")
        [['usplat', 'eval', '--out', 'a', '--data', 'b']]
    """
    joined = re.sub(r"\\\n", " ", block)
    return [tokens for line in joined.splitlines()
            if (tokens := shlex.split(line, comments=True))]


def flags(tokens: list[str]) -> list[str]:
    """The ``--flags`` among a command's arguments (``--flag=value`` counts as ``--flag``)."""
    return [t.split("=", 1)[0] for t in tokens if t.startswith("--")]


def run_sh_commands() -> set[str]:
    """The commands ``scripts/run.sh`` dispatches (its ``case "$command" in`` patterns)."""
    text = (ROOT / "scripts" / "run.sh").read_text()
    cases = text.split('case "$command" in', 1)[1].split("esac", 1)[0]
    return set(re.findall(r"^\s+([a-z][a-z-]*)\)", cases, re.MULTILINE))


def usplat_cli() -> list[str]:
    """The ``usplat`` entry point of this environment (``python -m usplat_dr`` without one)."""
    script = Path(sys.executable).with_name("usplat")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "usplat_dr"]


def help_has(help_text: str, flag: str) -> bool:
    """Whether ``flag`` appears in a help text as a whole option (``--out`` not ``--outdir``)."""
    return re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", help_text) is not None


def readme_commands() -> list[list[str]]:
    return [c for block in fenced_blocks(README.read_text(), "bash") for c in commands(block)]


# ---- Length and process words ----


def test_readme_is_a_front_door():
    n = len(README.read_text().splitlines())
    assert n <= MAX_LINES, f"README.md has {n} lines; move details into docs/ (<= {MAX_LINES})"


def test_the_demo_time_is_stated_once():
    # one constant: the CLI's help reads it, the README's command line must say the same
    from usplat_dr import DEMO_MINUTES
    from usplat_dr.cli import COMMANDS

    demo_line = next(line for line in README.read_text().splitlines()
                     if line.startswith("bash scripts/run.sh demo"))
    assert f"({DEMO_MINUTES} min on 2 CPU cores)" in demo_line, demo_line
    assert f"{DEMO_MINUTES} minutes" in COMMANDS["demo"]


def test_no_page_speaks_of_the_process():
    pages = [README, ROOT / "BENCHMARKS.md", *sorted((ROOT / "docs").glob("*.md")),
             *sorted((ROOT / "train").glob("*/README.md")), ROOT / "plugins" / "README.md"]
    hits = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}"
            for p in pages for i, line in enumerate(p.read_text().splitlines(), 1)
            if PROCESS_WORDS.search(line)]
    assert not hits, "process words (issue/stop numbers) in:\n" + "\n".join(hits)


#: The longest a Markdown page may be, logs and histories apart (their dated notes stand word
#: for word): a page past it is a notebook, and its reader wants an index.
MAX_PAGE_LINES = 600


def test_pages_read_as_pages():
    pages = [p for p in ROOT.glob("**/*.md")
             if not {".venv", "outputs", ".git", "node_modules"} & set(p.relative_to(ROOT).parts)
             and p.stem not in ("LOG", "history") and ".egg-info" not in str(p)]
    long = {str(p.relative_to(ROOT)): n for p in pages
            if (n := len(p.read_text().splitlines())) > MAX_PAGE_LINES}
    assert not long, (f"pages over {MAX_PAGE_LINES} lines (an index, with the notes in a "
                      f"LOG.md): {long}")


# ---- Links ----


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens.

    Examples:
        >>> slug("Speed against accuracy: `usplat bench`")
        'speed-against-accuracy-usplat-bench'
    """
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The anchors of a Markdown file's headings (headings inside code blocks excluded;
    repeated headings get GitHub's ``-1``, ``-2`` suffixes)."""
    text = re.sub(r"^```.*?^```", "", path.read_text(), flags=re.MULTILINE | re.DOTALL)
    seen: dict[str, int] = {}
    out = set()
    for heading in re.findall(r"^#{1,6} (.+)$", text, re.MULTILINE):
        base = slug(heading)
        out.add(f"{base}-{seen[base]}" if base in seen else base)
        seen[base] = seen.get(base, 0) + 1
    return out


def test_relative_links_resolve():
    pages = [README, ROOT / "BENCHMARKS.md", *sorted((ROOT / "docs").glob("*.md")),
             *sorted((ROOT / "train").glob("*/README.md"))]
    broken = []
    for page in pages:
        text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.MULTILINE | re.DOTALL)
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target):  # http(s):, mailto: -- not ours to check
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            where = f"{page.relative_to(ROOT)}: {target}"
            if not dest.exists():
                broken.append(f"{where} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                broken.append(f"{where} (no such heading)")
    assert not broken, "broken links:\n" + "\n".join(broken)


# ---- The commands, as pasted ----


def test_readme_commands_are_runnable_as_pasted():
    cmds = readme_commands()
    assert cmds, "the README shows no bash commands"
    usplat_flags: dict[str, set[str]] = {}
    train_overrides: list[tuple[list[str], list[str]]] = []
    scripts: dict[str, set[str]] = {}
    known_run_sh = run_sh_commands()
    for tokens in cmds:
        line = shlex.join(tokens)
        if tokens[0] == "usplat":
            args = [t for t in tokens[1:] if t not in ("-q", "--quiet", "--debug")]
            sub = args[0]
            usplat_flags.setdefault(sub, set()).update(flags(args[1:]))
            if sub == "train":
                configs = [args[i + 1] for i, t in enumerate(args) if t == "--config"]
                overrides = [t for t in args[1:] if "=" in t and not t.startswith("-")]
                train_overrides.append((configs or ["synthetic_tiny.yaml"], overrides))
        elif tokens[0] in ("python", "python3"):
            assert tokens[1] != "-m", f"add a check for 'python -m' commands: {line}"
            assert (ROOT / tokens[1]).is_file(), f"{tokens[1]} does not exist: {line}"
            scripts.setdefault(tokens[1], set()).update(flags(tokens[2:]))
        elif tokens[:2] == ["bash", "scripts/run.sh"]:
            assert len(tokens) > 2 and tokens[2] in known_run_sh, (
                f"scripts/run.sh knows {sorted(known_run_sh)}: {line}")
        else:
            pytest.fail(f"the README shows a command this test does not check: {line}")

    # Every help at once: each is a process importing torch (~2 s on a busy machine).
    jobs = {f"usplat {sub}": usplat_cli() + [sub, "--help"] for sub in usplat_flags}
    jobs |= {f"python {s}": [sys.executable, s, "--help"] for s in scripts}
    procs = {name: subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True)
             for name, argv in jobs.items()}
    helps = {}
    for name, proc in procs.items():
        out, _ = proc.communicate(timeout=TIMEOUT_S)
        assert proc.returncode == 0, f"{name} --help exited {proc.returncode}:\n{out}"
        helps[name] = out
    wanted = {f"usplat {k}": v for k, v in usplat_flags.items()}
    wanted |= {f"python {k}": v for k, v in scripts.items()}
    unknown = [f"{name} {flag}" for name, fl in wanted.items() for flag in sorted(fl)
               if not help_has(helps[name], flag)]
    assert not unknown, "flags the README passes that the command does not know:\n" + \
        "\n".join(unknown)

    # `usplat train`'s overrides: each names a key of the typed config, with a valid value.
    from usplat_dr.config import load_config
    from usplat_dr.training.config import RootCfg

    for configs, overrides in train_overrides:
        RootCfg.load(load_config(configs, overrides))


def test_readme_python_snippets(tmp_path):
    """The torch snippet runs as written (in a fresh process, in an empty folder); the others,
    which need the reader's data, compile and their imports resolve."""
    blocks = fenced_blocks(README.read_text(), "python")
    torch_snippets = [b for b in blocks if "from usplat_dr.render import" in b]
    assert len(torch_snippets) == 1, "the README should show one torch rasteriser snippet"
    imports = []
    for block in blocks:
        tree = ast.parse(block)  # a SyntaxError here names the README's bad line
        imports += [ast.unparse(node) for node in tree.body
                    if isinstance(node, (ast.Import, ast.ImportFrom))]
    code = "\n".join(imports) + "\n" + torch_snippets[0]
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=TIMEOUT_S, check=False)
    assert proc.returncode == 0, f"the README's Python failed:\n{proc.stderr[-3000:]}"


SPLIT_LABELS = {"standard": "standard (targets between the context views)",
                "extrapolation": "extrapolation (targets 1-4 frames beyond)"}


def verdict_rows(verdict: dict) -> list[str]:
    """The README's verdict rows as checkpoints/verdict.json gives them: the registered
    question (the paper's protocol with extrapolated training targets), standard then
    extrapolation split, 64x64 then 128x128; the seed-level interval."""
    rows = {}
    for s in verdict["sets"]:
        if "paper's protocol" not in s["arm"]:
            continue
        split = s["set"].split(" split")[0]
        if split not in SPLIT_LABELS:
            continue  # the wide-baseline rows live in docs/verdict.md
        size = "128x128" if "128x128" in s["set"] else "64x64"
        rows[(size, split)] = (f"| {SPLIT_LABELS[split]} | {size} | {s['mean']:+.3f} "
                               f"[{s['seed_low']:+.3f}, {s['seed_high']:+.3f}] | {s['seeds']} "
                               f"| **{s['label']}** |")
    return [rows[k] for k in sorted(rows, key=lambda k: (k[0] != "64x64", k[1] != "standard"))]


def test_readme_verdict_table_is_verdict_json():
    verdict = json.loads((ROOT / "checkpoints" / "verdict.json").read_text())
    expected = verdict_rows(verdict)
    assert len(expected) == 4, f"verdict.json gives {len(expected)} registered rows, not 4"
    lines = README.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("| held-out split |"))
    table = []
    for line in lines[header + 2:]:
        if not line.startswith("|"):
            break
        table.append(line)
    assert table == expected, ("the README's verdict table differs from checkpoints/"
                               "verdict.json; expected rows:\n" + "\n".join(expected))
