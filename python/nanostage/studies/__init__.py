"""Studies built on the library: the paper's step experiments (:mod:`.reproduce`), its ISO
230-2 campaigns (:mod:`.paper_campaigns`), the EMPS real-data study (:mod:`.emps`,
:mod:`.emps_study`) and the Table 1 tuning study (:mod:`.table1`).

A study may import anything in the package; nothing in the library imports a study.
"""
