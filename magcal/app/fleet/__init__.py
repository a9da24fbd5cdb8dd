"""``magcal fleet``: every log of a fleet analysed as ``fit`` analyses one, the rows kept in a
Parquet dataset as they finish, and each compass's history judged for changes
(``magcal.logic.fleet``). ``sources`` finds the files, ``analyse`` makes a file's rows (run in a
worker process or on a Dask worker), ``store`` keeps them, ``runner`` runs the tasks, ``page``
draws the fleet page."""
