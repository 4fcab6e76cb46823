#!/usr/bin/python3
"""Parameter tables of the nodes, read from the code that reads the parameters.

Every node reads its private parameters once, through `ros_params::number / integer / text /
flag / choice` (include/needle_guidance/ros/params.h), in src/ros/NODE_ros.cpp or
src/nodes/NODE_node.cpp. This script finds those calls and writes, in docs/nodes/NODE.md, the
table between the markers `<!-- params:begin -->` and `<!-- params:end -->`: name, type,
default, range and unit exactly as the code has them. The `meaning` column is kept from the page
(matched by parameter name), so it is the only hand-written part.

    scripts/node_params.py           rewrite the tables in docs/nodes/*.md
    scripts/node_params.py --check   exit 1 naming every page whose table differs from the code
"""
import pathlib
import re
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
BEGIN, END = "<!-- params:begin -->", "<!-- params:end -->"
CALL = re.compile(r"\b(?:ros_params|rp)::(number|integer|text|flag|choice)\s*\(")
HEADER = "| parameter | type | default | range | unit | meaning |\n| --- | --- | --- | --- | --- | --- |"


def call_arguments(text, start):
    """The top-level comma-separated arguments of the call whose '(' is at text[start - 1]."""
    depth, args, current, i, quote = 1, [], "", start, None
    while i < len(text) and depth > 0:
        c = text[i]
        if quote:
            current += c
            if c == "\\":
                current += text[i + 1]
                i += 1
            elif c == quote:
                quote = None
        elif c in "\"'":
            quote = c
            current += c
        elif c in "([{":
            depth += 1
            current += c
        elif c in ")]}":
            depth -= 1
            if depth > 0:
                current += c
        elif c == "," and depth == 1:
            args.append(current)
            current = ""
        else:
            current += c
        i += 1
    args.append(current)
    return [" ".join(a.split()) for a in args]


def literal(arg):
    m = re.fullmatch(r'"((?:[^"\\]|\\.)*)"', arg)
    return m.group(1) if m else None


def member_defaults():
    """member name -> set of default initialisers written in the core's public headers."""
    found = {}
    for header in (ROOT / "include/needle_guidance").rglob("*.h"):
        for m in re.finditer(r"^\s*[\w:<>, ]+?\b(\w+)\s*(?:=\s*([^;{}]+?)|\{([^;{}]*)\})\s*;",
                             header.read_text(), re.MULTILINE):
            value = (m.group(2) or m.group(3) or "").strip()
            if value and "(" not in value:
                found.setdefault(m.group(1), set()).add(value)
    return found


MEMBER_DEFAULTS = None


def shown_default(expr):
    """A default as the code writes it; a struct member's expression with its initialiser."""
    global MEMBER_DEFAULTS
    shown = literal(expr)
    if shown is not None:
        return f'"{shown}"'
    m = re.fullmatch(r"(?:\w+\.)+(\w+)", expr)
    if m and expr.split(".")[0] in ("options", "settings_", "defaults_", "pipeline"):
        if MEMBER_DEFAULTS is None:
            MEMBER_DEFAULTS = member_defaults()
        values = MEMBER_DEFAULTS.get(m.group(1), set())
        if len(values) == 1:
            return f"`{next(iter(values))}` (`{expr}`)"
    if expr.startswith("scene."):
        return f"the scene's (`{expr}`)"
    return f"`{expr}`"


def cell(value):
    return value.replace("|", "\\|")


def node_parameters(node):
    """(name, type, default, range, unit) per parameter of NODE, in the order the code reads them."""
    rows, seen = [], set()
    for path in (ROOT / "src/ros" / f"{node}_ros.cpp", ROOT / "src/nodes" / f"{node}_node.cpp"):
        if not path.exists():
            continue
        text = path.read_text()
        for m in CALL.finditer(text):
            kind, args = m.group(1), call_arguments(text, m.end())
            name = literal(args[1]) if len(args) > 1 else None
            if name is None or name in seen:  # a name built at run time is documented by hand
                continue
            seen.add(name)
            default, lower_upper, unit = (args[2] if len(args) > 2 else ""), "", ""
            if kind in ("number", "integer") and len(args) >= 6:
                lower_upper = f"[{args[3]}, {args[4]}]"
                unit = literal(args[5]) if literal(args[5]) is not None else args[5]
            elif kind == "choice" and len(args) >= 5:
                lower_upper = literal(args[4]) or args[4]
            elif kind == "text" and len(args) >= 4 and args[3] == "true":
                lower_upper = "required, not empty"
            default = shown_default(default)
            rows.append((name, "bool" if kind == "flag" else kind, default, lower_upper, unit))
    return rows


def meanings(page_text):
    """parameter name -> meaning cell, from the page's current table."""
    found = {}
    if BEGIN in page_text:
        block = page_text.split(BEGIN, 1)[1].split(END, 1)[0]
        for line in block.splitlines():
            cells = re.split(r"(?<!\\)\|", line)
            if len(cells) >= 8 and cells[1].strip().startswith("`~"):
                found[cells[1].strip().strip("`~")] = cells[6].strip()
    return found


def table(node, page_text):
    known = meanings(page_text)
    lines = [HEADER]
    for name, kind, default, rng, unit in node_parameters(node):
        lines.append(f"| `~{name}` | {kind} | {cell(default)} | {cell(rng)} | {cell(unit)} | "
                     f"{known.get(name, '')} |")
    return "\n".join(lines)


def main():
    check = "--check" in sys.argv[1:]
    stale = []
    for page in sorted((ROOT / "docs/nodes").glob("*.md")):
        text = page.read_text()
        if BEGIN not in text:
            continue
        head, rest = text.split(BEGIN, 1)
        tail = rest.split(END, 1)[1]
        updated = f"{head}{BEGIN}\n{table(page.stem, text)}\n{END}{tail}"
        if updated != text:
            stale.append(page.relative_to(ROOT))
            if not check:
                page.write_text(updated)
    if check and stale:
        print("node_params: parameter tables differ from the code in: " +
              ", ".join(map(str, stale)) + " (run scripts/node_params.py)", file=sys.stderr)
        return 1
    if not check:
        print(f"node_params: {len(stale)} page(s) updated")
    return 0


if __name__ == "__main__":
    if any(a in ("-h", "--help") for a in sys.argv[1:]):
        print(__doc__ + "\nusage: node_params.py [--check]")
        sys.exit(0)
    sys.exit(main())
