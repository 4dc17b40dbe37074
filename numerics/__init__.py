"""Numerical building blocks below every other layer (``numerics`` < ``tasks`` < ``models`` <
``estimators`` < ``harness``): linear algebra that never hands XLA a batched LAPACK call."""
