"""Many runs at once: `batch` over capture folders and every experiment, run one after another in this
process (`local`) or as Ray tasks on this machine's cores or a Ray cluster (`ray`). docs/design.md,
"Executors"."""
