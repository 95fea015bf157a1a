"""The training loop: `state` (RunState), `engine` (the compiled chunks), `host` (the loop
between them), `run_dir` (config.json and run directories). Methods import only `state`."""
