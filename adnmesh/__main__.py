"""Allow ``python -m adnmesh``."""

from adnmesh.cli import main

raise SystemExit(main())
