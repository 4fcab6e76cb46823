#!/usr/bin/python3
"""Checks that every core module includes only the headers of the modules it links.

CMakeLists.txt declares, for each core module, the modules it uses (NG_DEPS_<module> lists
needle_guidance_<other>); the link graph refuses a call into an undeclared module, but a header
of types or inline functions would slip through it. This check reads those declarations, closes
them transitively, and refuses any `#include "needle_guidance/<other>/..."` in
src/<module>/ or include/needle_guidance/<module>/ whose <other> module is neither the module
itself nor below it. The top-level headers (format.h, status.h, math.h, package_paths.h) belong
to every module.

    scripts/check_layering.py     exit 0 with a one-line summary, or exit 1 listing
                                  FILE:LINE: includes <other> (not below <module>)
"""
import pathlib
import re
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
INCLUDE = re.compile(r'^\s*#\s*include\s+"needle_guidance/(\w+)/')


def declared_modules(cmake_text):
    """{module: set of modules it links directly} from NG_CORE_MODULES and NG_DEPS_<module>."""
    text = re.sub(r"#[^\n]*", "", cmake_text)
    listed = re.search(r"set\(NG_CORE_MODULES([^)]*)\)", text)
    if not listed:
        sys.exit("check_layering: CMakeLists.txt has no set(NG_CORE_MODULES ...)")
    modules = listed.group(1).split()
    deps = {}
    for module in modules:
        found = re.search(rf"set\(NG_DEPS_{module}\b([^)]*)\)", text)
        if not found:
            sys.exit(f"check_layering: CMakeLists.txt sets no NG_DEPS_{module}")
        deps[module] = set(re.findall(r"needle_guidance_(\w+)", found.group(1))) & set(modules)
    return deps


def below(deps):
    """{module: every module it reaches through its declared dependencies}."""
    closed = {}
    for module in deps:
        seen, stack = set(), list(deps[module])
        while stack:
            other = stack.pop()
            if other not in seen:
                seen.add(other)
                stack.extend(deps.get(other, ()))
        closed[module] = seen
    return closed


def main(argv):
    if any(a in ("-h", "--help") for a in argv):
        print(__doc__.strip().replace("    scripts/", "usage: scripts/", 1))
        return 0
    deps = declared_modules((ROOT / "CMakeLists.txt").read_text())
    allowed = below(deps)
    hits, files = [], 0
    for module in sorted(deps):
        folders = [ROOT / "src" / module, ROOT / "include" / "needle_guidance" / module]
        for path in sorted(p for folder in folders if folder.is_dir() for p in folder.iterdir()):
            if path.suffix not in (".h", ".hpp", ".cpp"):
                continue
            files += 1
            for number, line in enumerate(path.read_text().splitlines(), 1):
                match = INCLUDE.match(line)
                if match and match.group(1) != module and match.group(1) not in allowed[module]:
                    hits.append(f"{path.relative_to(ROOT)}:{number}: includes {match.group(1)} "
                                f"(not below {module})")
    for hit in hits:
        print(hit)
    if hits:
        print(f"check_layering: {len(hits)} include(s) across the module layering "
              "(declare the module in NG_DEPS_<module> or move the code down)", file=sys.stderr)
        return 1
    print(f"[ci] ok: {files} files of {len(deps)} core modules include only modules below them")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
