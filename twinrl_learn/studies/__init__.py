"""The paper's studies, apart from the algorithms: the pipeline and its presets
(``twinrl demo``), Table I (``twinrl bench stage1``), the stages study (``twinrl bench
stages``) and their reports."""
