import sys

from gdwm.cli import main

sys.exit(main())
