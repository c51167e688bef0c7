#!/usr/bin/env bash
# Set-up steps of `make demo` / `make test` / `make install`, one step per call, one line per step on the
# terminal; the full apt/pip/npm output goes to the log ($MS3D_INSTALL_LOG, default $VENV/install.log).
# A failed step prints the log's last lines and the command to retry ($MS3D_RETRY), and exits non-zero.
#
#   deploy/install.sh apt LABEL PKG...  Debian packages, only the missing ones (sudo when not root)
#   deploy/install.sh python            the venv, pip, ms3d[dev] editable, the import check
#   deploy/install.sh node              Node.js >= 20 (Debian's when none), then `npm ci --prefix viewer`
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}
LOG=${MS3D_INSTALL_LOG:-$VENV/install.log}
RETRY=${MS3D_RETRY:-make install}
TAIL_LINES=20

mkdir -p "$(dirname "$LOG")"
[ -e "$LOG" ] || echo "ms3d install log (apt, pip and npm output of make's set-up steps)" >"$LOG"

step_start=0   # the log's line count when the current step began: a failure shows only its own lines
t_start=0

begin() {  # begin "what is installed": the step's line, completed by ok/fail
    step_start=$(wc -l <"$LOG")
    t_start=$SECONDS
    printf 'ms3d install: %s ... ' "$1"
    printf '\n==== %s  %s\n' "$(date '+%F %T')" "$1" >>"$LOG"
}

ok() {  # ok [note]
    local s=$((SECONDS - t_start)) note=${1:-}
    [ "$s" -ge 2 ] && note="${note:+$note, }${s} s"
    echo "ok${note:+ ($note)}"
}

fail() {  # fail "why": the log's tail (this step's lines only), the retry command; exits 1
    echo "FAILED"
    echo "ms3d install: $1"
    echo "---- last lines of $LOG ----"
    tail -n +"$((step_start + 1))" "$LOG" | tail -n "$TAIL_LINES"
    echo "----"
    echo "ms3d install: full output in $LOG; fix the cause above, then retry: $RETRY"
    exit 1
}

run() {  # run CMD...: its output to the log; a non-zero exit fails the step naming the command
    printf '$ %s\n' "$*" >>"$LOG"
    "$@" >>"$LOG" 2>&1 </dev/null || fail "\`$*\` failed (exit $?)"
}

SUDO=()  # root runs apt-get itself; anyone else through sudo
[ "$(id -u)" = 0 ] || SUDO=(sudo)

apt_install() {  # apt_install PKG...: apt-get update and install, into the log
    run "${SUDO[@]}" apt-get update -q
    run "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q "$@"
}

step_apt() {  # step_apt LABEL PKG...
    local label=$1 missing=() p
    shift
    begin "$label ($*)"
    for p in "$@"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
    if [ ${#missing[@]} -eq 0 ]; then
        echo "all of $* already installed" >>"$LOG"
        ok "already installed"
        return
    fi
    apt_install "${missing[@]}"
    ok "installed ${missing[*]}"
}

step_python() {
    local py=$VENV/bin/python ready
    if [ ! -x "$py" ]; then
        begin "Python virtual environment ($VENV)"
        run python3 -m venv "$VENV"
        ok
    fi
    begin "pip"
    run "$py" -m pip install --upgrade pip
    ok
    begin "Python packages (ms3d[dev], editable; a few minutes the first time)"
    run "$py" -m pip install -e ".[dev]" --config-settings editable_mode=compat
    ok
    begin "import check"
    printf '$ import open3d, torch, prefect, laspy\n' >>"$LOG"
    ready=$("$py" -c "import open3d, torch, prefect, laspy; print('torch', torch.__version__, 'open3d', open3d.__version__, 'prefect', prefect.__version__)" 2>>"$LOG") \
        || fail "the ms3d environment does not import (open3d, torch, prefect, laspy)"
    echo "$ready" >>"$LOG"
    ok "$ready"
}

step_node() {
    begin "Node.js >= 20"
    if ! command -v node >/dev/null; then
        apt_install nodejs npm
    fi
    node -e 'process.exit(parseInt(process.versions.node) >= 20 ? 0 : 1)' \
        || fail "ms3d needs Node.js >= 20 for the viewer and the glTF validator (found $(node --version))"
    ok "$(node --version)"
    begin "npm packages of the viewer (viewer/node_modules)"
    command -v npm >/dev/null || apt_install npm
    run npm ci --prefix viewer --no-audit --no-fund --no-progress
    ok
}

case ${1:-} in
    apt) shift; [ $# -ge 2 ] || { echo "usage: $0 apt LABEL PKG..." >&2; exit 2; }; step_apt "$@" ;;
    python) step_python ;;
    node) step_node ;;
    *) echo "usage: $0 apt LABEL PKG... | python | node" >&2; exit 2 ;;
esac
