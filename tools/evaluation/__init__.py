"""The studies of the papers: ``evaluate`` (``fieldlog evaluate``: the distributed-KF paper's outage study, its
Table 3) and ``studies`` (``fieldlog study``: the other papers' tables), both scoring fused solutions against the
truth or the withheld GPS."""
