import sys

from fluoapp.cli import main

sys.exit(main())
