"""What more than one stage needs, so that no stage borrows from another.

A layer between the stages (:mod:`cca_cli.stages`: one file in, one file out,
each on its own) and the file formats, config and numeric core below them:

* :mod:`~cca_cli.workflows.scenes` – the simulated object from the scene section,
  and its bar and USAF tables;
* :mod:`~cca_cli.workflows.recording` – noisy simulated images and the captures file;
* :mod:`~cca_cli.workflows.recovery` – choosing an engine and running it to a result;
* :mod:`~cca_cli.workflows.multiplex` – the multiplexed-illumination branches of
  simulate, reconstruct and report.

Nothing here imports :mod:`cca_cli.stages` or :mod:`cca_cli.commands`.
"""
