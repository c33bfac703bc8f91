"""``python -m replay inspect|show|export PATH ...`` (see replay.inspect)."""

import sys

from replay.inspect import cli

if __name__ == "__main__":
    sys.exit(cli(sys.argv[1:]))
