#!/usr/bin/env bash
# Compiles the Unity-independent core (Runtime/Core) and Tests/TestMain.cs with mono's mcs (C# 7.2, the
# same source Unity compiles), checks every golden vector in protocol/vectors, then runs a live session
# against an `ofera serve` this script starts on a free port and stops at exit.
# Installs nothing: needs `mcs` and `mono` (Debian: apt-get install mono-mcs mono-runtime), and for the
# live part the `ofera` command (pip install -e .) and python3.
#
# Environment:
#   OFERA_STUB_LIVE=0              skip the live server part (vectors and unit tests only)
#   OFERA_STUB_URL=ws://h:p/v1/stream  use an already running server instead of starting one
#   OFERA_STUB_SERVER_ARGS="..."   extra arguments for `ofera serve` (e.g. --avatars DIR)
#   OFERA_STUB_SERVER_TIMEOUT=300  seconds to wait for /healthz
#   OFERA_STUB_FRAMES=100          frames in the live session
#   OFERA_STUB_BENCH_RIG=1         only print the C# params deformation time as one JSON line (RigTests.Bench): the
#                                  server's default rig when the live part runs, else a synthetic rig of that size
# Ends with the test program's closing line "N passed, N failed"; exit status non-zero if any failed.
set -u

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
PKG="$(dirname "$HERE")"
REPO="$(dirname "$PKG")"
VECTORS="$REPO/protocol/vectors"
PYTHON="${PYTHON:-python3}"

for tool in mcs mono; do
    if ! command -v "$tool" >/dev/null 2>&1; then
        echo "run.sh: '$tool' not found; install mono first (Debian/Ubuntu: apt-get install -y mono-mcs mono-runtime)" >&2
        echo "0 passed, 1 failed"
        exit 2
    fi
done

BUILD="$(mktemp -d "${TMPDIR:-/tmp}/ofera-unity-stub.XXXXXX")"
SERVER_PID=""
cleanup() {
    if [ -n "$SERVER_PID" ] && kill -0 "$SERVER_PID" 2>/dev/null; then
        kill "$SERVER_PID" 2>/dev/null
        for _ in $(seq 1 50); do kill -0 "$SERVER_PID" 2>/dev/null || break; sleep 0.1; done
        kill -9 "$SERVER_PID" 2>/dev/null
    fi
    rm -rf "$BUILD"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

echo "== compiling Runtime/Core with $(mcs --version) (-langversion:7.2)"
# System.dll holds System.Net.WebSockets.ClientWebSocket on mono; nothing else is referenced.
if ! mcs -langversion:7.2 -nologo -warn:4 -target:library -r:System.dll \
        -out:"$BUILD/Ofera.Client.Core.dll" "$PKG"/Runtime/Core/*.cs; then
    echo "0 passed, 1 failed"; exit 1
fi
if ! mcs -langversion:7.2 -nologo -warn:4 -r:System.dll -r:"$BUILD/Ofera.Client.Core.dll" \
        -out:"$BUILD/TestMain.exe" "$HERE/TestMain.cs" "$HERE/DeltaTests.cs" "$HERE"/Room*.cs "$HERE/RigTests.cs"; then
    echo "0 passed, 1 failed"; exit 1
fi
# The Unity-side scripts need UnityEngine.dll, which this machine does not have: they are type-checked
# against Tests/UnityStandIn.cs (stand-ins for the members they use; FaceLogRecorder.cs, which needs
# more of UnityEngine, is left out), with every optional assembly's define on, and on again without v60.
echo "== type-checking Runtime/Unity against Tests/UnityStandIn.cs"
for SDK60 in -define:OFERA_META_SDK_60 ""; do
    # shellcheck disable=SC2086
    if ! mcs -langversion:7.2 -nologo -warn:4 -target:library -r:System.dll -r:"$BUILD/Ofera.Client.Core.dll" \
            -define:OFERA_GAUSSIAN_SPLATTING -define:OFERA_META_SDK $SDK60 -out:"$BUILD/UnityTypeCheck.dll" \
            "$HERE/UnityStandIn.cs" "$PKG"/Runtime/Unity/OferaAvatarClient.cs "$PKG"/Runtime/Unity/Sinks.cs \
            "$PKG"/Runtime/Unity/FaceSources.cs "$PKG"/Runtime/Unity/MemberPoseSource.cs \
            "$PKG"/Runtime/Unity/GaussianSplatting/GaussianSplattingSink.cs "$PKG"/Runtime/Unity/GaussianSplatting/RigSplattingSink.cs \
            "$PKG"/Runtime/Unity/MetaQuest/OvrFaceSource.cs; then
        echo "0 passed, 1 failed"; exit 1
    fi
done

ARGS=(--vectors "$VECTORS" --frames "${OFERA_STUB_FRAMES:-100}")
if command -v "$PYTHON" >/dev/null 2>&1 && "$PYTHON" -c "import ofera.sources" >/dev/null 2>&1; then
    ARGS+=(--python "$PYTHON")
fi

SERVER_FAILED=""
if [ "${OFERA_STUB_LIVE:-1}" != "0" ]; then
    if [ -n "${OFERA_STUB_URL:-}" ]; then
        ARGS+=(--live "$OFERA_STUB_URL")
    elif ! command -v ofera >/dev/null 2>&1; then
        SERVER_FAILED="the 'ofera' command is not installed (pip install -e . at the repository root)"
    else
        PORT="$("$PYTHON" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1]); s.close()')"
        LOG="$BUILD/serve.log"
        echo "== starting: ofera serve --host 127.0.0.1 --port $PORT ${OFERA_STUB_SERVER_ARGS:-}"
        # shellcheck disable=SC2086
        ofera serve --host 127.0.0.1 --port "$PORT" --log-level warning ${OFERA_STUB_SERVER_ARGS:-} >"$LOG" 2>&1 &
        SERVER_PID=$!
        DEADLINE=$(( $(date +%s) + ${OFERA_STUB_SERVER_TIMEOUT:-300} ))
        READY=""
        while [ "$(date +%s)" -lt "$DEADLINE" ]; do
            if ! kill -0 "$SERVER_PID" 2>/dev/null; then break; fi
            if "$PYTHON" -c "import sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:$PORT/healthz', timeout=2).status == 200 else 1)" >/dev/null 2>&1; then
                READY=1; break
            fi
            sleep 1
        done
        if [ -n "$READY" ]; then
            echo "== server ready on port $PORT"
            ARGS+=(--live "ws://127.0.0.1:$PORT/v1/stream")
        else
            SERVER_FAILED="ofera serve did not answer /healthz within ${OFERA_STUB_SERVER_TIMEOUT:-300} s; its log ends with:
$(tail -n 15 "$LOG" 2>/dev/null)"
        fi
    fi
fi

if [ "${OFERA_STUB_BENCH_RIG:-0}" = "1" ]; then
    # one JSON line: the C# params deformation time (the live server's default rig, else a synthetic rig of its size)
    mono "$BUILD/TestMain.exe" --bench-rig "${ARGS[@]}"
    exit $?
fi

mono --debug "$BUILD/TestMain.exe" "${ARGS[@]}" | tee "$BUILD/out.txt"
STATUS=${PIPESTATUS[0]}
LAST="$(tail -n 1 "$BUILD/out.txt")"

if [ -n "$SERVER_FAILED" ]; then
    # The live part could not run: count it as one failure and restate the closing line.
    echo "FAIL live server: $SERVER_FAILED"
    P="$(echo "$LAST" | sed -n 's/^\([0-9]*\) passed, \([0-9]*\) failed$/\1/p')"
    F="$(echo "$LAST" | sed -n 's/^\([0-9]*\) passed, \([0-9]*\) failed$/\2/p')"
    echo "${P:-0} passed, $(( ${F:-0} + 1 )) failed"
    exit 1
fi
if [ "$STATUS" -ne 0 ]; then exit "$STATUS"; fi
case "$LAST" in
    *" passed, 0 failed") exit 0 ;;
    *) exit 1 ;;
esac
