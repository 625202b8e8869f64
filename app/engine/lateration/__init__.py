"""Least-squares position fixes with their a-priori accuracy (Grinyak 2020).

``accuracy``: the measurement model (ranges, path loss) and the three checks of
a linearised fix (rank, condition number, ``D = (Hᵀ Q⁻¹ H)⁻¹``), which need no
measurement. ``solver``: robust Gauss–Newton over a batch of problems, each
fix checked and given a status.
"""
