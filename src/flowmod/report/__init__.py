"""What readers see: figures (:mod:`~flowmod.report.viz`), videos (:mod:`~flowmod.report.video`),
the world's chapter helpers (:mod:`~flowmod.report.world_report`), the book's assembly
(:mod:`~flowmod.report.book`) and its browser check (:mod:`~flowmod.report.browser`)."""
