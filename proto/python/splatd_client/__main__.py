"""``python3 -m splatd_client --selftest-emit PATH | --selftest-check PATH`` (see the package docs)."""

import sys

from splatd_client import _main

sys.exit(_main(sys.argv[1:]))
