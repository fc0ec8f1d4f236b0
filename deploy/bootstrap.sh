#!/bin/sh
# triswarm bootstrap: installs a triswarm release on a drone's onboard computer. `triswarm deploy` copies it to
# the target with the release's files and runs it there over SSH; it also works by hand (POSIX sh, Linux).
#
#   bootstrap.sh install  --root DIR --release NAME --from DIR [--python PY] [--system-site-packages]
#                         [--no-deps] [--service-user USER] [--no-service] [--remove-from]
#   bootstrap.sh rollback --root DIR              switch back to the previous release (twice: forward again)
#   bootstrap.sh abort    --root DIR --release NAME   undo the install of NAME if it is still current
#   bootstrap.sh status   --root DIR              print current=... and previous=...
#
# Layout under the install root (default /opt/triswarm):
#   venv/                   the Python environment of the dependencies (numpy, scipy, numba, zenoh, ...),
#                           created once with --python (default python3, >= 3.11) and reused
#   releases/NAME/          one release: lib/ (triswarm itself, pip --target), bin/triswarm-companion,
#                           companion.toml, signing.key (0600), triswarm-companion.service, the wheel,
#                           what the configuration names (a plan, a Zenoh configuration; with deploy --pki:
#                           pki/ca.pem, pki/agent-<i>.pem, pki/agent-<i>.key (0600), pki/agent-<i>.json5)
#   current -> releases/NAME    the release in force, switched atomically (rename of a symlink)
#   previous -> releases/NAME   the one before, kept for rollback; an install keeps one more (the previous
#                               previous, for abort) and deletes the others
#   bootstrap.sh            this script (for rollback and abort later)
#
# install: --from holds the wheel (one *.whl), companion.toml, triswarm-companion.service, optionally
# signing.key and files/ (copied next to companion.toml); --remove-from deletes it at the end. NAME is <version>-<hash of what is shipped>; a
# NAME that is already current changes nothing ("unchanged"). The dependencies are installed into venv/
# from the wheel's metadata, then triswarm into the new release; the release must import, then `current`
# switches to it. Where systemd runs ([ -d /run/systemd/system ]) and as root, it creates the service user
# (triswarm, no login, home /var/lib/triswarm), installs the unit, enables it and restarts the companion,
# which must still be running 3 s later. Without systemd it says so and skips the service. Any failure
# after the switch switches back and restarts the previous release.
#
# Options for machines that already have the dependencies:
#   --system-site-packages  create venv/ so that it sees the interpreter's own packages (e.g. Debian's
#                           python3-numpy, python3-scipy: quicker than pip on a small computer)
#   --no-deps               install no dependencies at all: venv/ must already provide them. For images
#                           made with the dependencies, and for the tests, whose venv/ is made in advance
#                           with a .pth file pointing at the development environment (tests only).

set -eu

SERVICE=triswarm-companion.service
UNIT_DIR=/etc/systemd/system

say() { printf 'bootstrap: %s\n' "$*"; }
die() { printf 'bootstrap: error: %s\n' "$*" >&2; exit 1; }

usage() { sed -n '2,/^$/p' "$0" | sed 's/^# \{0,1\}//' >&2; exit 2; }

[ $# -ge 1 ] || usage
ACTION=$1
shift
ROOT= RELEASE= FROM= PY=python3 SYSTEM_SITE=0 NO_DEPS=0 SERVICE_USER=triswarm NO_SERVICE=0 REMOVE_FROM=0
while [ $# -gt 0 ]; do
    case $1 in
        --root) ROOT=${2:?}; shift 2 ;;
        --release) RELEASE=${2:?}; shift 2 ;;
        --from) FROM=${2:?}; shift 2 ;;
        --python) PY=${2:?}; shift 2 ;;
        --system-site-packages) SYSTEM_SITE=1; shift ;;
        --no-deps) NO_DEPS=1; shift ;;
        --service-user) SERVICE_USER=${2:?}; shift 2 ;;
        --no-service) NO_SERVICE=1; shift ;;
        --remove-from) REMOVE_FROM=1; shift ;;
        -h|--help) usage ;;
        *) die "unknown option $1" ;;
    esac
done
[ -n "$ROOT" ] || die "--root DIR is required"
case $ROOT in /*) ;; *) die "--root must be an absolute path, got $ROOT" ;; esac
case $ROOT$SERVICE_USER in *[!A-Za-z0-9._/+-]*) die "--root and --service-user may hold only letters, digits and ._/+-" ;; esac
ROOT=${ROOT%/}
if [ -n "$RELEASE" ]; then
    case $RELEASE in
        *[!A-Za-z0-9._+-]*|.*) die "bad release name $RELEASE" ;;
    esac
fi
VENV=$ROOT/venv
PYBIN=$VENV/bin/python
export PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_ROOT_USER_ACTION=ignore PIP_NO_INPUT=1

release_of() {  # release name a symlink points to, or nothing
    if [ -L "$1" ]; then basename "$(readlink "$1")"; fi
}

set_link() {  # set_link NAME RELEASE: point ROOT/NAME at releases/RELEASE atomically (RELEASE empty: remove)
    if [ -z "$2" ]; then
        rm -f "$ROOT/$1"
        return
    fi
    rm -f "$ROOT/.$1.new"
    ln -s "releases/$2" "$ROOT/.$1.new"
    mv -T "$ROOT/.$1.new" "$ROOT/$1"
}

systemd_here() { [ -d /run/systemd/system ] && command -v systemctl >/dev/null 2>&1; }

manage_service() {  # 0 if this run installs and restarts the service
    [ "$NO_SERVICE" = 0 ] || return 1
    systemd_here || return 1
    [ "$(id -u)" = 0 ] || return 1
}

service_note() {
    if [ "$NO_SERVICE" = 1 ]; then
        say "service: skipped (--no-service)"
    elif ! systemd_here; then
        say "service: systemd is not running here (no /run/systemd/system): not installed; the unit is" \
            "$ROOT/current/$SERVICE, start the companion with $ROOT/current/bin/triswarm-companion --config" \
            "$ROOT/current/companion.toml"
    else
        say "service: not root, so the unit is not installed (run bootstrap as root: triswarm deploy --sudo)"
    fi
}

restart_service() {  # install the current release's unit, restart, and make sure it keeps running
    if ! id -u "$SERVICE_USER" >/dev/null 2>&1; then
        say "creating the service user $SERVICE_USER"
        useradd --system --user-group --home-dir /var/lib/triswarm --no-create-home \
            --shell /usr/sbin/nologin "$SERVICE_USER"
    fi
    for key in "$ROOT/current/signing.key" "$ROOT"/current/pki/*.key; do
        if [ -f "$key" ]; then
            chown "$SERVICE_USER:" "$key"
            chmod 600 "$key"
        fi
    done
    install -m 644 "$ROOT/current/$SERVICE" "$UNIT_DIR/$SERVICE.new"
    mv -f "$UNIT_DIR/$SERVICE.new" "$UNIT_DIR/$SERVICE"
    systemctl daemon-reload
    systemctl enable --quiet "$SERVICE"
    systemctl reset-failed "$SERVICE" >/dev/null 2>&1 || true
    systemctl restart "$SERVICE"
    sleep 3
    state=$(systemctl is-active "$SERVICE" || true)
    [ "$state" = active ] || die "$SERVICE is $state 3 s after its restart (journalctl -u ${SERVICE%.service})"
    say "service: $SERVICE enabled and running"
}

lock() {
    mkdir -p "$ROOT/releases"
    if command -v flock >/dev/null 2>&1; then
        exec 9>"$ROOT/.lock"
        flock -w 60 9 || die "another bootstrap holds $ROOT/.lock"
    fi
}

# --------------------------------------------------------------------------------------------------------------

do_status() {
    echo "current=$(release_of "$ROOT/current")"
    echo "previous=$(release_of "$ROOT/previous")"
}

do_rollback() {
    lock
    cur=$(release_of "$ROOT/current")
    prev=$(release_of "$ROOT/previous")
    [ -n "$prev" ] && [ -f "$ROOT/releases/$prev/.complete" ] || die "no previous release to roll back to"
    set_link current "$prev"
    set_link previous "$cur"
    rm -f "$ROOT/.last-install"  # nothing left to abort
    say "rolled back: current = $prev (previous = $cur)"
    if manage_service; then restart_service; else service_note; fi
}

do_abort() {
    [ -n "$RELEASE" ] || die "abort needs --release NAME"
    lock
    cur=$(release_of "$ROOT/current")
    if [ "$cur" != "$RELEASE" ]; then
        say "abort: $RELEASE is not current (current = ${cur:-none}), nothing to undo"
        return 0
    fi
    [ -f "$ROOT/.last-install" ] || die "abort: no record of the install of $RELEASE"
    read -r name old_cur old_prev created < "$ROOT/.last-install" || true
    [ "$name" = "$RELEASE" ] || die "abort: the last install was $name, not $RELEASE"
    [ "$old_cur" = - ] && old_cur=
    [ "$old_prev" = - ] && old_prev=
    undo_switch "$old_cur" "$old_prev" "$created"
}

undo_switch() {  # undo_switch OLD_CURRENT OLD_PREVIOUS CREATED(1: delete releases/RELEASE)
    set_link current "$1"
    set_link previous "$2"
    rm -f "$ROOT/.last-install"
    if [ "$3" = 1 ]; then rm -rf "$ROOT/releases/$RELEASE"; fi
    if [ -n "$1" ]; then
        say "rolled back to $1"
        if manage_service; then
            restart_service ||
                say "warning: the previous release's service did not start either"
        fi
    else
        say "rolled back: no release installed any more"
        if manage_service; then systemctl disable --now --quiet "$SERVICE" || true; fi
    fi
}

# install ------------------------------------------------------------------------------------------------------

SWITCHED=0 CREATED=0 OLD_CUR= OLD_PREV= STAGE=

on_exit() {
    status=$?
    trap - EXIT
    if [ "$status" != 0 ]; then
        [ -z "$STAGE" ] || rm -rf "$STAGE"
        if [ "$SWITCHED" = 1 ]; then
            say "install of $RELEASE failed: rolling back"
            undo_switch "$OLD_CUR" "$OLD_PREV" "$CREATED" || true
        elif [ "$CREATED" = 1 ]; then
            rm -rf "$ROOT/releases/$RELEASE"
        fi
    fi
    if [ "$REMOVE_FROM" = 1 ] && [ -d "$FROM" ]; then rm -rf "$FROM"; fi
    exit "$status"
}

make_venv() {
    if [ -x "$PYBIN" ] && "$PYBIN" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
        say "venv: reusing $VENV"
        return
    fi
    command -v "$PY" >/dev/null 2>&1 || die "no Python interpreter $PY (give --python)"
    "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' ||
        die "$PY is Python $("$PY" -c 'import sys; print(sys.version.split()[0])'); triswarm needs >= 3.11"
    rm -rf "$VENV"
    if [ "$SYSTEM_SITE" = 1 ]; then
        say "venv: creating $VENV with $PY, seeing its site-packages (--system-site-packages)"
        "$PY" -m venv --system-site-packages "$VENV"
    else
        say "venv: creating $VENV with $PY"
        "$PY" -m venv "$VENV"
    fi
}

install_deps() {
    if [ "$NO_DEPS" = 1 ]; then
        say "dependencies: not installed (--no-deps): $VENV must provide them"
        return
    fi
    reqs=$STAGE/requirements.txt
    "$PYBIN" - "$WHEEL" > "$reqs" <<'EOF'
import email.parser, re, sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as z:
    meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
    msg = email.parser.Parser().parsestr(z.read(meta).decode("utf-8"))
for req in msg.get_all("Requires-Dist") or []:
    if not re.search(r"\bextra\s*==", req):
        print(req)
EOF
    say "dependencies: $(wc -l < "$reqs" | tr -d ' ') requirements into $VENV (pip; this takes a while the first time)"
    "$PYBIN" -m pip install --quiet --upgrade-strategy only-if-needed -r "$reqs"
}

build_release() {  # in releases/RELEASE itself (the paths compiled into the .pyc files stay true); complete
    dest=$ROOT/releases/$RELEASE
    CREATED=1
    mkdir -p "$dest/bin" "$dest/wheel"
    cp "$WHEEL" "$dest/wheel/"
    "$PYBIN" -m pip install --quiet --no-deps --no-cache-dir --no-warn-script-location --target "$dest/lib" "$WHEEL"
    cp "$FROM/companion.toml" "$dest/"
    sed -e "s#/opt/triswarm#$ROOT#g" -e "s#^User=triswarm\$#User=$SERVICE_USER#" \
        -e "s#^Group=triswarm\$#Group=$SERVICE_USER#" "$FROM/$SERVICE" > "$dest/$SERVICE"
    if [ -d "$FROM/files" ]; then
        # a certificate's key (pki/agent-<i>.key) is 0600 before it is copied, and so from the start
        find "$FROM/files" -type f -name '*.key' -exec chmod 600 {} +
        cp -R "$FROM/files/." "$dest/"
    fi
    if [ -f "$FROM/signing.key" ]; then
        (umask 077 && cp "$FROM/signing.key" "$dest/signing.key")
        chmod 600 "$dest/signing.key"
    fi
    cat > "$dest/bin/triswarm-companion" <<EOF
#!/bin/sh
# triswarm-companion of release $RELEASE (written by bootstrap.sh): this release's code, venv/'s dependencies.
PYTHONPATH="$dest/lib\${PYTHONPATH:+:\$PYTHONPATH}"
export PYTHONPATH
exec "$PYBIN" -s -P -c 'import sys; sys.argv[0] = "triswarm-companion"; from triswarm.companion.cli import main; main()' "\$@"
EOF
    chmod 755 "$dest/bin/triswarm-companion"
    {
        echo "release=$RELEASE"
        echo "wheel=$(basename "$WHEEL")"
        echo "installed=$(date -u +%Y-%m-%dT%H:%M:%SZ)"
        echo "python=$("$PYBIN" -c 'import sys; print(sys.version.split()[0])')"
    } > "$dest/RELEASE"
    # The release must import with venv/'s dependencies before it can become current.
    PYTHONPATH="$dest/lib" "$PYBIN" -s -P -c 'import triswarm.companion.cli, triswarm.companion.config' ||
        die "release $RELEASE does not import with $VENV (missing dependencies? see above)"
    touch "$dest/.complete"
}

do_install() {
    [ -n "$RELEASE" ] || die "install needs --release NAME"
    [ -n "$FROM" ] && [ -d "$FROM" ] || die "install needs --from DIR (the release's files)"
    trap on_exit EXIT
    lock
    OLD_CUR=$(release_of "$ROOT/current")
    OLD_PREV=$(release_of "$ROOT/previous")
    if [ "$OLD_CUR" = "$RELEASE" ] && [ -f "$ROOT/releases/$RELEASE/.complete" ]; then
        say "unchanged: $RELEASE is already current"
        return 0
    fi
    set -- "$FROM"/*.whl
    [ $# = 1 ] && [ -f "$1" ] || die "--from must hold exactly one wheel"
    WHEEL=$1
    for f in companion.toml "$SERVICE"; do [ -f "$FROM/$f" ] || die "--from has no $f"; done
    umask 022
    make_venv
    STAGE=$(mktemp -d "$ROOT/releases/.new-XXXXXX")
    install_deps
    if [ -f "$ROOT/releases/$RELEASE/.complete" ]; then
        say "release: $RELEASE already there (the previous one), switching back to it"
    else
        rm -rf "$ROOT/releases/$RELEASE"
        say "release: installing $(basename "$WHEEL") as $RELEASE"
        build_release
    fi
    rm -rf "$STAGE"
    STAGE=

    # the switch: previous <- current <- RELEASE
    printf '%s %s %s %s\n' "$RELEASE" "${OLD_CUR:--}" "${OLD_PREV:--}" "$CREATED" > "$ROOT/.last-install"
    SWITCHED=1
    if [ -n "$OLD_CUR" ]; then set_link previous "$OLD_CUR"; fi
    set_link current "$RELEASE"
    say "current = $RELEASE (previous = ${OLD_CUR:-none})"
    cp "$FROM/bootstrap.sh" "$ROOT/.bootstrap.sh.new" 2>/dev/null && mv -f "$ROOT/.bootstrap.sh.new" "$ROOT/bootstrap.sh" || true

    if manage_service; then restart_service; else service_note; fi
    SWITCHED=0

    # keep the new release, the one it replaced (previous) and the one before that (what `abort` restores as
    # previous if the check that follows fails); delete the rest
    for d in "$ROOT"/releases/* "$ROOT"/releases/.new-*; do
        [ -e "$d" ] || continue
        n=$(basename "$d")
        if [ "$n" != "$RELEASE" ] && [ "$n" != "$OLD_CUR" ] && [ "$n" != "$OLD_PREV" ]; then
            say "deleting old release $n"
            rm -rf "$d"
        fi
    done
}

case $ACTION in
    install) do_install ;;
    rollback) do_rollback ;;
    abort) do_abort ;;
    status) do_status ;;
    *) usage ;;
esac
