"""``python -m otbot_hw`` = the ``otbot`` command."""
import sys

from otbot_hw.cli import main

sys.exit(main())
