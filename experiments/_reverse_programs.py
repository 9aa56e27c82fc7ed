"""The backward step loop of reverse mode with the CPU flags before 2026-11-28 (issue 40),
kept here so that experiments can measure it beside the library's: each step's VJP taken
with respect to its start state and the field's parameters, one step after another
(crank_jax/solve/adjoint.py now takes the parameters' part after the loop, `_deferred`).

`per_step(params=True)` has `adjoint._deferred`'s signature; patch it in with
`adjoint._deferred = per_step()` before tracing a gradient. With `params=False` it is a
diagnostic, not a gradient: the steps' VJPs leave the parameters out, so their cotangents
are never formed (zero, tied to the state's cotangent so that XLA keeps the loop).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def per_step(params: bool = True):
    from crank_jax.solve import adjoint

    def make(full, arithmetic, dd, pack, unpack, window, B, n_state):
        # (`arithmetic`, the field with its trig as arithmetic, is the deferred VJPs'; the
        # per-step loop takes the field as the forward pass ran it.)
        def outputs(row, tw, dd):
            return adjoint._step_outputs(full(dd), pack, unpack, row, tw, n_state)

        def block(rows, kb, size, carry):
            blk = jax.lax.dynamic_slice_in_dim(rows, kb * B, B)
            tws, gws = jax.vmap(window)(blk)
            n = jnp.minimum(size - kb * B, B)

            def one(k, carry):
                ybar, dbar = carry
                i = n - 1 - k
                row, tw, gw = blk[i], tws[i], gws[i]
                wrt = dd if params else []
                _, pull = jax.vjp(lambda y, d: outputs(row.at[3:].set(y), tw,
                                                       d if params else dd), row[3:], wrt)
                yb, db = pull((ybar, gw))
                if not params:
                    return yb, [d + 0.0 * yb[0] for d in dbar]
                return yb, [a + b for a, b in zip(dbar, db)]

            return jax.lax.fori_loop(0, n, one, carry)

        return block

    return make
