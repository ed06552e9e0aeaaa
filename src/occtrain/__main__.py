from occtrain.cli import main

raise SystemExit(main())
