#!/usr/bin/python3
"""Refuses words about how the software was developed in tracked files (code, comments, docs,
config, launch files, tests, scripts): bug-tracker numbers, work-session numbers, ordinal
rounds of work, the names of who did it, references to files outside the repository, and
tuning diaries (the patterns below list them). The product describes what it does and why; history belongs in CHANGELOG.md as
release notes, which this check reads too.

Words that only look alike are allowed: "tissue", "passes through", "bypass", a gate that a
detection "passes", and the afterloader's delivery "session" (a start or resume of a plan on the
device, a record kind of its journal).

    scripts/check_product_words.py     exit 1 listing FILE:LINE: text for every hit
"""
import pathlib
import re
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
ORDINAL = r"(?:first|second|third|fourth|fifth|sixth|next|this|last|previous|earlier|later)"
PATTERNS = [
    (r"\bissues?\s*#?\d+", "a tracker number"),
    (r"\bsessions?\s*#?\d+|\bwritten in session\b", "a work-session number"),
    (rf"\b{ORDINAL}\s+pass(?:es)?\b(?!\s+(?:through|over|of the (?:mesh|data|loop)))",
     "a development pass"),
    (r"\bhelpers?\b", "'helper' (name what it does)"),
    (r"(?-i:\b(?:STYLE|DESIGN|ROS_ON_DEBIAN)\.md\b)", "a file outside the repository"),
    (r"\bnothing kept\b|\bmeasured and not kept\b|\btuning diary\b", "a tuning diary"),
]
COMPILED = [(re.compile(p, re.IGNORECASE), why) for p, why in PATTERNS]
SKIP = {"scripts/check_product_words.py"}  # states the patterns themselves


def tracked_text_files():
    names = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z"], capture_output=True,
                           check=True).stdout.decode().split("\0")
    for name in names:
        path = ROOT / name
        if not name or name in SKIP or not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:  # binary
            continue
        yield name, data.decode("utf-8", errors="replace")


def main():
    hits = 0
    for name, text in tracked_text_files():
        for number, line in enumerate(text.splitlines(), 1):
            for pattern, why in COMPILED:
                match = pattern.search(line)
                if match:
                    hits += 1
                    print(f"{name}:{number}: {why}: '{match.group(0)}': {line.strip()[:140]}")
    if hits:
        print(f"check_product_words: {hits} development-process word(s); write what the software "
              "does and why instead", file=sys.stderr)
        return 1
    print("check_product_words: ok")
    return 0


if __name__ == "__main__":
    if any(a in ("-h", "--help") for a in sys.argv[1:]):
        print(__doc__ + "\nusage: check_product_words.py")
        sys.exit(0)
    sys.exit(main())
