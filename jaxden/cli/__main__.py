import sys

from jaxden.cli import main

sys.exit(main())
