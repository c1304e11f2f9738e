import sys

from mapless.cli import main

sys.exit(main())
