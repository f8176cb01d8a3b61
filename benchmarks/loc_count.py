"""Lines of code per package and per file: code lines (tokenize-based) and `wc -l` lines.

A code line is a physical line holding at least one token that is not a comment, a docstring or layout
(NEWLINE, NL, INDENT, DEDENT). A docstring is a string expression standing alone as a statement (module,
class, function docstrings and any other bare string statement). Issue 12's "Lines of code" figure counts
the `pipeline` package this way.

    python benchmarks/loc_count.py                       # pipeline/ at the working tree, per file
    python benchmarks/loc_count.py pipeline frontends    # several packages
    python benchmarks/loc_count.py --rev 1a2b3c pipeline # a package as it was at a commit (git show)
    python benchmarks/loc_count.py --totals pipeline     # one line per package
"""

from __future__ import annotations

import argparse
import io
import subprocess
import sys
import tokenize
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAYOUT_TOKENS = {tokenize.NEWLINE, tokenize.NL, tokenize.INDENT, tokenize.DEDENT, tokenize.COMMENT,
                 tokenize.ENDMARKER, tokenize.ENCODING}


@dataclass(frozen=True)
class FileCount:
    path: str
    code_lines: int
    wc_lines: int


def docstring_lines(tokens: list[tokenize.TokenInfo]) -> set[int]:
    """Lines of string tokens that make up a statement of their own (a docstring or a bare string)."""
    lines: set[int] = set()
    at_statement_start = True
    index = 0
    while index < len(tokens):
        token = tokens[index]
        if token.type in (tokenize.NEWLINE, tokenize.NL, tokenize.INDENT, tokenize.DEDENT):
            at_statement_start = at_statement_start or token.type != tokenize.NL
            index += 1
            continue
        if token.type == tokenize.COMMENT:
            index += 1
            continue
        if at_statement_start and token.type == tokenize.STRING:
            run_end = index
            while run_end + 1 < len(tokens) and tokens[run_end + 1].type in (tokenize.STRING, tokenize.NL):
                run_end += 1
            following = tokens[run_end + 1] if run_end + 1 < len(tokens) else None
            ends_statement = (tokenize.NEWLINE, tokenize.ENDMARKER, tokenize.COMMENT)
            if following is None or following.type in ends_statement:
                for string_token in tokens[index:run_end + 1]:
                    lines.update(range(string_token.start[0], string_token.end[0] + 1))
        at_statement_start = token.type == tokenize.OP and token.string == ";"
        index += 1
    return lines


def count_source(path: str, source: str) -> FileCount:
    tokens = list(tokenize.generate_tokens(io.StringIO(source).readline))
    skipped = docstring_lines(tokens)
    code: set[int] = set()
    for token in tokens:
        if token.type in LAYOUT_TOKENS:
            continue
        code.update(line for line in range(token.start[0], token.end[0] + 1) if line not in skipped)
    return FileCount(path, len(code), source.count("\n") + (0 if source.endswith("\n") or not source else 1))


def python_files(package: str, rev: str | None) -> dict[str, str]:
    """Source of every .py file below `package`, from the working tree or from commit `rev`."""
    if rev is None:
        return {str(path.relative_to(REPO)): path.read_text(encoding="utf-8")
                for path in sorted((REPO / package).rglob("*.py"))}
    listing = subprocess.run(["git", "-C", str(REPO), "ls-tree", "-r", "--name-only", rev, "--", package],
                             check=True, capture_output=True, text=True).stdout.split()
    return {name: subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:{name}"], check=True,
                                 capture_output=True, text=True).stdout
            for name in sorted(listing) if name.endswith(".py")}


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("packages", nargs="*", default=["pipeline"])
    parser.add_argument("--rev", help="count the packages as they were at this commit")
    parser.add_argument("--totals", action="store_true", help="one line per package, no per-file rows")
    args = parser.parse_args(argv)
    print(f"at {args.rev or 'the working tree'}\n")
    print("| file | code lines | wc -l |\n|---|---:|---:|")
    for package in args.packages:
        counts = [count_source(path, source) for path, source in python_files(package, args.rev).items()]
        if not args.totals:
            for count in sorted(counts, key=lambda item: -item.code_lines):
                print(f"| {count.path} | {count.code_lines} | {count.wc_lines} |")
        print(f"| **{package}/ ({len(counts)} files)** | **{sum(c.code_lines for c in counts)}** "
              f"| **{sum(c.wc_lines for c in counts)}** |")


if __name__ == "__main__":
    main(sys.argv[1:])
