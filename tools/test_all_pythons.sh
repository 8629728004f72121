#!/usr/bin/env bash
# usage: tools/test_all_pythons.sh [-h] [-- PYTEST_ARGUMENTS...]
#
# Run the test suite on every supported CPython (3.10-3.13) found on this machine, one after the other,
# each in a fresh venv made with the README's install command; and check that every unsupported
# CPython found (3.7-3.9, 3.14, 3.15) is stopped by that command with one line.
#
#   tools/test_all_pythons.sh                       # the whole suite on each version
#   tools/test_all_pythons.sh -- -m "not slow"      # the fast subset; pytest's arguments go after --
#   tools/test_all_pythons.sh -h                    # this help (--help too)
#
# Pythons are looked up as python3.X on PATH and under $PYENV_ROOT/versions (default ~/.pyenv);
# venvs are made under $VBD_PYTHONS_DIR (default ~/.cache/vbd-taichi/pythons) and replaced each run.
# Prints one result line per version and exits non-zero if any version failed.

set -uo pipefail
while [ $# -gt 0 ]; do
    case "$1" in
        -h | --help)    # the comment above, without its '#'
            sed -n '2,/^$/s/^# \{0,1\}//p' "$0"
            exit 0 ;;
        --)
            shift
            break ;;
        *)
            echo "error: unknown argument '$1'; pytest's arguments go after --, for example: $0 -- -m 'not slow'" \
                 "(see $0 --help)" >&2
            exit 2 ;;
    esac
done
cd "$(dirname "$0")/.."
venvs=${VBD_PYTHONS_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/vbd-taichi/pythons}
pyenv_root=${PYENV_ROOT:-$HOME/.pyenv}
mkdir -p "$venvs"

find_python() {   # the newest python3.$1 found, or nothing
    local found
    found=$(ls -d "$pyenv_root"/versions/3."$1".*/bin/python3 2>/dev/null | sort -V | tail -n 1)
    [ -n "$found" ] || found=$(command -v "python3.$1" 2>/dev/null)
    [ -n "$found" ] && echo "$found"
}

results=()
failed=0
supported=0
for minor in 7 8 9 10 11 12 13 14 15; do
    python=$(find_python "$minor") || continue
    version=$("$python" -c 'import platform; print(platform.python_version())')
    venv="$venvs/$version"
    rm -rf "$venv"
    log="$venvs/$version.log"
    if [ "$minor" -lt 10 ] || [ "$minor" -gt 13 ]; then
        echo "== $version (unsupported): the README's install command must stop with one line"
        "$python" -m venv "$venv" && "$venv/bin/pip" install -q -r requirements.txt -e . >"$log" 2>&1
        status=$?
        lines=$(grep -v '^WARNING: ' "$log" | grep -c .)     # pip's warnings, if any, are not the error
        if [ "$status" -ne 0 ] && [ "$lines" -eq 1 ] && grep -q "pyenv install 3.13" "$log"; then
            results+=("$version: stopped with one line (ok): $(grep '^ERROR' "$log")")
        else
            results+=("$version: FAILED: install exit $status, $lines lines, see $log")
            failed=1
        fi
        rm -rf "$venv"
        continue
    fi
    supported=$((supported + 1))
    echo "== $version: fresh venv in $venv, install, pytest $*"
    start=$(date +%s)
    if ! { "$python" -m venv "$venv" && "$venv/bin/pip" install -q -r requirements.txt -e .; } >"$log" 2>&1; then
        results+=("$version: FAILED: install, see $log")
        failed=1
        continue
    fi
    "$venv/bin/python" -m pytest -q -p no:cacheprovider "$@" 2>&1 | tee -a "$log" | tail -n 1
    status=${PIPESTATUS[0]}
    summary=$(tail -n 1 "$log")
    seconds=$(( $(date +%s) - start ))
    if [ "$status" -eq 0 ]; then
        results+=("$version: $summary (install + tests ${seconds} s)")
    else
        results+=("$version: FAILED: $summary, see $log")
        failed=1
    fi
done

echo
echo "== $(date -u +%Y-%m-%d) pytest $*"
printf '%s\n' "${results[@]}"
if [ "$supported" -eq 0 ]; then
    echo "no CPython 3.10-3.13 found (pyenv install 3.13, or uv python install 3.13)"
    exit 1
fi
exit $failed
