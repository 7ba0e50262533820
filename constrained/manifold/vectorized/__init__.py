"""The vectorized build (issue 28): a large model's repeated rows and terms evaluated as whole
columns of instances in CasADi's virtual machine, and the KKT solve's products with J written
on J's nonzeros by index data (``columns``: column arithmetic and sums; ``build``: the index
data of a structure; ``graphs``: the acceleration and the projections on it)."""
