import sys

from millsense.daemon.cli import main

sys.exit(main())
