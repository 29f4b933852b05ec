from tsnav.cli import main

raise SystemExit(main())
