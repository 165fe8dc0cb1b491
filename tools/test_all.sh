#!/usr/bin/env bash
# Run the test suite on every supported Python (3.10 to 3.13) with freshly resolved dependencies.
#
#   tools/test_all.sh [PYTEST_ARGS...]        (what `make test-all` runs)
#   VERSIONS="3.11 3.13" tools/test_all.sh    (only these)
#
# For each version: the newest pyenv build of it (${PYENV_ROOT:-~/.pyenv}/versions/3.X.N), else
# python3.X on PATH. .venv-3.X is deleted and rebuilt (so pip resolves numpy, scipy, numba, ...
# anew), `pip install -e '.[test]'` runs in it, then pytest, with a numba cache of its own
# (.venv-3.X/numba-cache: kernels compiled against another numpy are never reused). The versions
# run one after the other (timing tests share 2 cores badly). At the end one line per version;
# exit status 1 if any failed. A version without an interpreter counts as failed, not skipped: a
# green run must mean that every version requires-python admits was tested (VERSIONS= narrows
# the set on purpose).
set -u
cd "$(dirname "$0")/.." || exit 2
root=$PWD
versions=${VERSIONS:-3.10 3.11 3.12 3.13}

find_python() {  # $1 = 3.X; prints an interpreter that reports exactly 3.X, or nothing
    local v=$1 cand
    local pyenv_versions=${PYENV_ROOT:-$HOME/.pyenv}/versions
    for cand in $( (ls -d "$pyenv_versions/$v".* 2>/dev/null | grep -E "/${v//./\\.}\.[0-9]+$" | sort -V -r
                    command -v "python$v") 2>/dev/null); do
        [[ -d $cand ]] && cand=$cand/bin/python
        if [[ -x $cand ]] && [[ $("$cand" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null) == "$v" ]]; then
            echo "$cand"
            return 0
        fi
    done
    return 1
}

summary=()
failed=0
for v in $versions; do
    venv=$root/.venv-$v
    echo "=== Python $v ==="
    if ! py=$(find_python "$v"); then
        summary+=("$v: FAILED - no interpreter (no ${PYENV_ROOT:-~/.pyenv}/versions/$v.N, no working python$v on PATH)")
        failed=1
        continue
    fi
    full=$("$py" -c 'import platform; print(platform.python_version())')
    rm -rf -- "$venv"
    if ! { "$py" -m venv "$venv" && "$venv/bin/python" -m pip install -q --disable-pip-version-check \
             -e "$root[test]"; } >"$root/.venv-$v.install.log" 2>&1; then
        tail -n 20 "$root/.venv-$v.install.log"
        summary+=("$v: FAILED - $full: venv or pip install failed (.venv-$v.install.log)")
        failed=1
        continue
    fi
    mv "$root/.venv-$v.install.log" "$venv/install.log"
    deps=$("$venv/bin/python" -c 'import numpy, scipy, numba
print(f"numpy {numpy.__version__}, scipy {scipy.__version__}, numba {numba.__version__}")' 2>&1 | tail -n 1)
    echo "$full: $deps"
    NUMBA_CACHE_DIR=$venv/numba-cache "$venv/bin/python" -m pytest -q -p no:cacheprovider "$@" 2>&1 \
        | tee "$venv/pytest.log"
    rc=${PIPESTATUS[0]}
    tally=$(grep -E '^=*.* in [0-9.]+s' "$venv/pytest.log" | tail -n 1 | sed -E 's/^=+ //; s/ =+$//')
    if [[ $rc == 0 ]]; then
        summary+=("$v: passed - $full ($deps): $tally")
    else
        summary+=("$v: FAILED - $full ($deps): pytest exit $rc: ${tally:-no summary} (.venv-$v/pytest.log)")
        failed=1
    fi
done

echo
echo "=== test-all ==="
printf '%s\n' "${summary[@]}"
exit $failed
