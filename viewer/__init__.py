"""The local web viewer of `fullview view`: 3-D scene, virtual tour, correlated views, hand-point picker."""
