"""Dense output between accepted samples, for methods without an interpolant of their own."""

from __future__ import annotations


def hermite(t0: float, x0, v0, a0, t1: float, x1, v1, a1, acceleration=None):
    """(x(t), v(t)) on [t0, t1] from the ends: quintic Hermite when a is known at both ends
    (error O(h⁶)), else cubic Hermite in x (its derivative for v).

    ``acceleration(t, x, v)``: with it the quintic is corrected to degree 6 by one more
    acceleration, at the midpoint: the quintic's error is x⁽⁶⁾ h⁶ s³(s − 1)³ / 720 (s the
    fraction of the step), so adding c·s³(1 − s)³ — which leaves x, v, a at both ends as they
    are — with c chosen so that the second derivative at s = ½ is the acceleration there,

        c = −(8/3) h² (a(½) − a_H(½)),   a_H(½) = 1.5 (v1 − v0)/h − 0.25 (a0 + a1),

    removes that error term (what is left is O(h⁷)). Computed the first time it is needed."""
    h = t1 - t0
    correction = []  # [c], once asked for

    def corrected(t: float):
        x, v = at(t)
        if acceleration is None or a0 is None or a1 is None or not h:
            return x, v
        if not correction:
            xm, vm = at(t0 + 0.5 * h)
            a_hermite = 1.5 * (v1 - v0) / h - 0.25 * (a0 + a1)
            correction.append(-(8.0 / 3.0) * h * h * (acceleration(t0 + 0.5 * h, xm, vm) - a_hermite))
        s = (t - t0) / h
        c = correction[0]
        return x + c * (s * (1 - s)) ** 3, v + c * 3 * (s * (1 - s)) ** 2 * (1 - 2 * s) / h

    def at(t: float):
        s = (t - t0) / h if h else 1.0
        if a0 is None or a1 is None:
            b = (2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2)
            db = (6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s)
            x = b[0] * x0 + b[1] * h * v0 + b[2] * x1 + b[3] * h * v1
            v = (db[0] * x0 + db[1] * h * v0 + db[2] * x1 + db[3] * h * v1) / h if h else v1
            return x, v
        s2, s3, s4, s5 = s * s, s**3, s**4, s**5
        b = (1 - 10 * s3 + 15 * s4 - 6 * s5, s - 6 * s3 + 8 * s4 - 3 * s5,
             0.5 * (s2 - 3 * s3 + 3 * s4 - s5), 10 * s3 - 15 * s4 + 6 * s5,
             -4 * s3 + 7 * s4 - 3 * s5, 0.5 * (s3 - 2 * s4 + s5))
        db = (-30 * s2 + 60 * s3 - 30 * s4, 1 - 18 * s2 + 32 * s3 - 15 * s4,
              s - 4.5 * s2 + 6 * s3 - 2.5 * s4, 30 * s2 - 60 * s3 + 30 * s4,
              -12 * s2 + 28 * s3 - 15 * s4, 1.5 * s2 - 4 * s3 + 2.5 * s4)
        x = b[0] * x0 + b[1] * h * v0 + b[2] * h * h * a0 + b[3] * x1 + b[4] * h * v1 + b[5] * h * h * a1
        v = (db[0] * x0 + db[1] * h * v0 + db[2] * h * h * a0 + db[3] * x1 + db[4] * h * v1
             + db[5] * h * h * a1) / h if h else v1
        return x, v

    return corrected
