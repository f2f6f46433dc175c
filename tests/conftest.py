import jax

# float64 available for the tests that ask for it (float32 stays the default
# for arrays the tests create with an explicit dtype); strict promotion catches
# silent float32/float64 mixing.
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
