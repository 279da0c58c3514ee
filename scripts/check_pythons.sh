#!/usr/bin/env bash
# Install sparsecomm on other Pythons, or at its dependencies' lower bounds, and run quick tests.
#
#   scripts/check_pythons.sh [--worktree] [--lowest] PYTHON [PYTHON ...]
#
# For each PYTHON (a path, or a name on PATH) it makes, in a new temporary folder:
#   1. a fresh copy of this repository: `git clone` of the committed HEAD, or with --worktree the
#      working tree's tracked and untracked (not ignored) files, uncommitted edits included;
#   2. a fresh venv made by PYTHON;
#   3. the install: the README's test command up to its `&&` (today
#      `pip install -c requirements-lock.txt -e ".[test]"`, the exact versions CI uses); or, with
#      --lowest, `uv pip install --resolution lowest-direct -e ".[test]"`: every direct
#      dependency of pyproject.toml at the lowest version its range allows (uv is pip-installed
#      into the venv first; the lock file is not used);
#   4. `python -m pytest -q $TESTS` (default TESTS: tests/test_channel.py tests/test_env.py).
# It prints one line per PYTHON (ok, or the step that failed and its log) and exits non-zero if
# any failed. Environment: TESTS (pytest arguments), KEEP=1 keeps the temporary folders (else
# each is removed after a success), TMPDIR (where they go). Each Python needs network access to
# the package index, about 1.5 GB of disk, and a few minutes. docs/install.md records the results.
set -uo pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
worktree=0
lowest=0
pythons=()
for arg in "$@"; do
    case "$arg" in
        --worktree) worktree=1 ;;
        --lowest) lowest=1 ;;
        -h | --help) awk 'NR > 1 && /^#/ {sub(/^# ?/, ""); print; next} NR > 1 {exit}' "$0"; exit 0 ;;
        *) pythons+=("$arg") ;;
    esac
done
if [ ${#pythons[@]} -eq 0 ]; then
    echo "usage: $0 [--worktree] [--lowest] PYTHON [PYTHON ...]" >&2
    exit 2
fi
read -r -a tests <<<"${TESTS:-tests/test_channel.py tests/test_env.py}"

# The README's test command is the second line of its first bash block; install = before `&&`.
install_command() {
    awk '/^```bash/{n++; next} n==1 && /^```/{exit} n==1{print}' "$1/README.md" \
        | sed -n 2p | sed 's/ *&&.*//'
}

failed=0
for py in "${pythons[@]}"; do
    work=$(mktemp -d "${TMPDIR:-/tmp}/sparsecomm-check.XXXXXX")
    log="$work/log.txt"
    step=copy
    (
        set -e
        if [ "$worktree" = 1 ]; then
            mkdir "$work/repo"
            (cd "$repo" && git ls-files -z --cached --others --exclude-standard \
                | tar --null -T - --ignore-failed-read -cf - 2>/dev/null) | tar -xf - -C "$work/repo"
        else
            git clone -q "$repo" "$work/repo"
        fi
    ) >>"$log" 2>&1 && step=venv && "$py" -m venv "$work/venv" >>"$log" 2>&1 && step=install && (
        set -e
        cd "$work/repo"
        . "$work/venv/bin/activate"
        python --version
        python -m pip install -q --upgrade pip
        if [ "$lowest" = 1 ]; then
            python -m pip install -q uv
            uv pip install --resolution lowest-direct -e ".[test]"
        else
            install=$(install_command .)
            case "$install" in
                "pip install "*) echo "$install"; eval "$install" ;;
                *) echo "cannot read the install command from README.md: '$install'"; exit 1 ;;
            esac
        fi
        python -m pip freeze --exclude-editable >"$work/freeze.txt"
    ) >>"$log" 2>&1 && step=tests && (
        cd "$work/repo"
        . "$work/venv/bin/activate"
        python -m pytest -q -p no:cacheprovider "${tests[@]}"
    ) >>"$log" 2>&1 && step=ok
    version=$("$py" --version 2>/dev/null || echo "$py")
    if [ "$step" = ok ]; then
        versions=$(grep -iE '^(jax|jaxlib|flax|optax|numpy|scipy|tyro|matplotlib|pillow|pettingzoo|gymnasium)==' \
            "$work/freeze.txt" | tr '\n' ' ')
        echo "$version: ok ($(tail -n 1 "$log")) with $versions"
        [ "${KEEP:-0}" = 1 ] || rm -rf "$work"
    else
        echo "$version: FAILED at $step; log: $log"
        tail -n 5 "$log" | sed 's/^/    /'
        failed=1
    fi
done
exit $failed
