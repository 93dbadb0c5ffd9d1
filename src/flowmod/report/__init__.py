"""What readers see: figures and tables (:mod:`~flowmod.report.viz`), videos
(:mod:`~flowmod.report.video`), the book's assembly (:mod:`~flowmod.report.book`) and its
browser check (:mod:`~flowmod.report.browser`). Each chapter's own tables and numbers are in
:mod:`flowmod.chapters`."""
