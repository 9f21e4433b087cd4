# Sourced by the tools' run scripts: makes DIR/.venv on first use and installs
# DIR/requirements.txt into it (pinned versions; quiet when nothing changes).
#   . tools/python-venv.sh && python_venv DIR     # then DIR/.venv/bin/python
python_venv() {
    if [ ! -x "$1/.venv/bin/python" ]; then
        python3 -m venv "$1/.venv"
    fi
    "$1/.venv/bin/pip" install --quiet --disable-pip-version-check -r "$1/requirements.txt"
}
