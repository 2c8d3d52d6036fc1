"""Many runs: dataset recipes (`datasets/*.yaml`), running them in batches (serially or on a
Dask cluster), parameter sweeps and searches, and the summary across runs."""
