"""Where a run is put together: its directory and config.json (`run_dir`), its engine with
the method's hooks (`build`), training it (`build.train`) and reading a trained one back
(`restore`). Train, grid, the lab's dataset builder and the run-reading tools use these."""
