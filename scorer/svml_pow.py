"""numpy's `power` as it computes it on AVX-512 machines (Intel SVML's `__svml_pow8_ha`), on every host.

PDM-Closed's IDM takes (v / v0) ** 10 every step (`pdm_closed.idm_step`). On AVX-512 CPUs numpy (2.x) runs
SVML's pow, elsewhere the C library's, and the two differ by an ulp on about 5 % of the IDM's bases: SVML's is
not correctly rounded (5 % of x ** 10 for x in [0, 2] differ from the correctly rounded value), so no
correctly rounded computation can stand for it, and the C library's nearly is one. The official results come
from AVX-512 machines, so `power_avx512` gives SVML's bits: numpy's own where numpy runs SVML, this replay
elsewhere (docs/engine.md, "Host dependence and kernels").

The replay is SVML's operations one by one, so it is exact by construction, not by tuning: every operation is
an IEEE operation on doubles whose result is defined bit for bit. It gives this host's SVML bits on every one of
millions of random and near-tie bases, and SVML's recorded bits on every host (tests/test_svml_pow.py).

- Main path, positive finite bases (subnormal ones too) with |W| <= 1021.5, W = y log2 x (for the exponent
  10: about 2^-102 <= x <= 2^102.15): each FMA emulated exactly (`geometry._fused_multiply_add`), the roundings
  toward zero and downward that SVML asks of a few operations emulated exactly (`scorer.directed_rounding`),
  `vrcp14pd` from its table (`scorer.rcp14`), and `vgetmantpd`, `vgetexppd`, `vrndscalepd` and `vreducepd`,
  which are exact, by `frexp`, `round` and `floor` (vreducepd's final subtraction rounds downward); tables and
  coefficients from `__svml_dpow_ha_data_internal_avx512` (2^(j/16) and the shifter are exp's, `scorer.svml_exp`).
  log2 x = e + log2 m for x = m 2^e, m in [1/2, 1): m times r (`vrcp14pd`'s estimate of 1/m rounded to 1/32)
  is near 1, log2 m = log2(m r) - log2 r with -log2 r (or 1 - log2 r, e one less) from a 32-entry table;
  log2(m r) = log2(1 + 2u), u = (m r - 1) / 2, a polynomial whose first two terms are kept in double-double.
  W is formed in double-double rounded toward zero, then 2^W = 2^n 2^(j/16) 2^f with 2^(j/16) from a 16-entry
  table and 2^f a polynomial.
- SVML's scalar path (`__svml_dpow_ha_cout_rare_internal`) for every other lane: negative, zero, infinite and
  NaN bases, an infinite or NaN exponent, |W| > 1021.5. Plain SSE2 operations rounded to nearest one by one
  (no FMA), tables `__dpow_ha_CoutTab`: log2 |x| in double-double through three reciprocal tables, y log2 |x|
  = N / 128 + t from Dekker-split products, 2^(N / 128) from a 128-entry table, 2^t a polynomial; results below
  2^-1022 formed 2^200 larger and scaled down. A negative base with an odd integer exponent negates |x| ** y;
  with a non-integer one it gives NaN. Its special cases (x ** 0 = 1 ** y = 1, (-1) ** ±inf = 1, zero and
  infinite bases and exponents, NaN) come first, in its order. It differs from the main path's bits for |x| on
  about 5 % of bases (it is more accurate: about 0.1 % of its tenth powers are not correctly rounded), so a
  negative base is not the main path's |x| ** y with a sign. The IDM's base is negative where the ego's speed
  is (`IdmUnroll` does not clip it at 0).
"""

from __future__ import annotations

import base64
import zlib

import numpy as np
import numpy.typing as npt

from scorer.directed_rounding import (
    add_downward,
    add_toward_zero,
    fused_multiply_add_toward_zero,
    multiply_toward_zero,
)
from scorer.geometry import FloatArray, _fused_multiply_add
from scorer.rcp14 import rcp14
from scorer.svml_exp import EXP2_16THS_HI, EXP2_16THS_LO, SIXTEENTHS_SHIFTER, hex_table

# -log2 r as high (22-34 bits) + low part, for r = 1 + i/32 (i = 0 .. 15, e stays) and, for r in [1.5, 2),
# 1 - log2 r (i = 16 .. 31, e one less); r = 2 takes entry 0.
_LOG_HI = hex_table(
    "0x0.0p+0", "-0x1.6bad3758e0000p-5", "-0x1.663f6fac90000p-4", "-0x1.08c588cda8000p-3",
    "-0x1.5c01a39fc0000p-3", "-0x1.acf5e2db50000p-3", "-0x1.fbc16b9028000p-3", "-0x1.24407ab0e0000p-2",
    "-0x1.49a784bcd0000p-2", "-0x1.6e221cd9d0000p-2", "-0x1.91bba891f0000p-2", "-0x1.b47ebf7388000p-2",
    "-0x1.d6753e0330000p-2", "-0x1.f7a8568cb0000p-2", "-0x1.0c10500d64000p-1", "-0x1.1bf311e95e000p-1",
    "0x1.a8ff971810000p-2", "0x1.8a8980abfc000p-2", "0x1.6cb0f6865c000p-2", "0x1.4f6fbb2cec000p-2",
    "0x1.32bfee3710000p-2", "0x1.169c053640000p-2", "0x1.f5fd8a9060000p-3", "0x1.bfc67a8000000p-3",
    "0x1.8a8980abf8000p-3", "0x1.563dc29ff8000p-3", "0x1.22dadc2ab0000p-3", "0x1.e0b1ae8f30000p-4",
    "0x1.7d60496d00000p-4", "0x1.1bb32a6000000p-4", "0x1.77394c9da0000p-5", "0x1.743ee86200000p-6",
)  # fmt: skip
_LOG_LO = hex_table(
    "0x0.0p+0", "-0x1.fb0e626c0de13p-42", "-0x1.3167ccc538261p-44", "0x1.871a7610e40bdp-45",
    "0x1.4bc302ffa76fbp-42", "0x1.36c101ee13440p-43", "0x1.7f5dc57266758p-43", "-0x1.ce60916e52e91p-44",
    "-0x1.b8afe492bf6ffp-42", "-0x1.9bcaf1aa4168ap-43", "-0x1.708b4b2b5056cp-42", "-0x1.50520a377c7ecp-45",
    "0x1.5f101c141e670p-42", "-0x1.b3b3864c60011p-44", "0x1.5669df6a2b592p-43", "0x1.fe43895d8ac46p-42",
    "0x1.4bc302ffa76fbp-43", "-0x1.66cccab240e90p-45", "0x1.1d406db502403p-43", "0x1.661e393a16b95p-44",
    "-0x1.1979a5db68722p-42", "-0x1.d4f1b95e0ff45p-43", "0x1.f1a4847f7b278p-42", "-0x1.667f21fa8423fp-44",
    "0x1.e9933354dbf17p-42", "0x1.6590643906f2ap-42", "0x1.a4b69691d7994p-42", "-0x1.54cda62d3926ep-47",
    "-0x1.12ce6312ebb82p-42", "0x1.52743318a8a57p-42", "-0x1.4e55443478fe0p-42", "-0x1.95539356f93dcp-43",
)  # fmt: skip
_TWO_OVER_LN2 = float.fromhex("0x1.71547652b82fep+1")  # log2(1 + 2u) = (2 / ln 2)(u - u^2 + ...)
# The rest of log2(1 + 2u) as pairs (a, b) = a u + b, highest first, combined in SVML's order (below); the
# last pair is the low parts of the first two terms.
_LOG_PAIRS = tuple(
    (float.fromhex(a), float.fromhex(b))
    for a, b in (
        ("-0x1.27a394386376fp+7", "0x1.4873cf87141d1p+6"),
        ("-0x1.715473528efc1p+5", "0x1.a617607e55815p+4"),
        ("-0x1.ec709dc3b71a1p+3", "0x1.2776c50effbdep+3"),
        ("-0x1.71547652b82fcp+2", "0x1.ec709dc3a03fdp+1"),
        ("-0x1.778d9c7190437p-55", "0x1.777df70b75d10p-55"),
    )
)
# 2^f - 1 over f as pairs a f + b, highest first.
_EXP2_PAIRS = tuple(
    (float.fromhex(a), float.fromhex(b))
    for a, b in (
        ("0x1.4a1d7f58c2d59p-13", "0x1.5d7472783d279p-10"),
        ("0x1.3b2ad1b14ebaap-7", "0x1.c6b08d4ad8eb9p-5"),
        ("0x1.ebfbdff84554dp-3", "0x1.62e42fefa398bp-1"),
    )
)
_MAIN_PATH_W = 1021.5  # |W| above it (or NaN): SVML's scalar path
_EXPONENT_MASK = 0x7FF0000000000000

# SVML's scalar path (`__dpow_ha_CoutTab`), read off numpy's SVML: log2 x from three reciprocal tables (33, 33
# and 129 entries; the third times 1 / ln 2) with -log2 of each as high + low, and 2^(i/128) as high + low;
# little-endian doubles, zlib-compressed, base64.
_SCALAR_TABLES = np.frombuffer(
    zlib.decompress(
        base64.b64decode(
            "eNp913k4Ft//P/CpFFoQWZJKSSTKvmR43WSNbNn3vXorUWkhuq2VUrbsZEm70qJ1dG4pFXpTlLKENi3Ivst3ppnPdf1+3+tzfecP"
            "j+t5nznbzBxzBsOoow+ovxzu33/FVvTSWa+HNrib/r3k11/ZAz+Zclp25g86j3+nsxctq76L/t2Qll3xjc76tOyXX+nz7Gixb19o"
            "wxiX0LJufqazDS175BP9ex6jKS022km3f5EWc2Fc3Mn010GfH0OL6TFi//H/PVbmz3p0AYJbtPa7Z+I6GDZmucPvLpTC5YSBGEUd"
            "jMMX1XSKA9yz7yx+tllNB/NM9DXhPIMd6h4Rjc9kdbCO9XMU66rBPwl9VNHYQOa0zwZEHWja+suO3zbWwUrfJBZvfgNujT++h2ST"
            "7deLFTRmNcKF2tn7NF4Z6mACv5NlPr0DrcQIvjWWSjqY1c6818s+wPaqkS+6j7aS5+vK+Jm0gNfKPN4tZVvI86UkM7e3AVfI9zSr"
            "HjEdLGh/nmpoO0gmfYgMCiTLsTorkYoOKLZZ/MtG1EgHyzgdqI86wd5j7q6ZfzR0MJaaRO6ZZmSbYWk5zGVUjilyxa++/B7FvE+o"
            "kyRMyzHWla7MmndoPXbxrfN6vXIMi3Y7N9KIjK6bvdk9qFmOBZWNCcs3IOXk5R2fAheVY6WWDWo7X6PimATVKutV5Vh+cMQVjzr0"
            "xOaZ5AFhnXKsw2W561QN0izT50uMkSHLTXhLLr9A9s4Dvg9PmJPtB8yU+DxDlatTuTV4tpZjnvtnDyo8QTpuVk8+myiS4+lNTuV5"
            "jI4dfTt1wo5VjrHz9VIa7yG7K6PEWK8FWe5cF0LcROnReUK3wsn67KiK6UMXkcq2GwPxGqpk+6FK4frpKLV0jlk/ZlyO/deDXhdY"
            "H7MuOn4zzzUtm0PLKWXKC5jfk5gcxeS9TPZhzt/G/G7AtKfGlK9lsiHTrx6jDrM+NRlVadmKjPKMsrSsNYySjBKMYkx7SxgFGBcy"
            "8jByMf5n/v/fIXueb9l2MP59IGPHUVPyudrB+SB5EGqfH9IYFjcgc2h8lWEkHPflZL0up/Ibr6HpOBgd+WA0lUetI1e18funwOnO"
            "ZMnLEGUyq3UHaCdBi1yl5R1pfjIfCBMRSAXRbT2XFh4Hqj0l6W9p0LLE3pcPyHWBzdqdWZ4JVxXEVePeyZO5/vT+tBzgWvDaP2HM"
            "gsySjT2+56BZ9nhU5WLq/OR0b/ECeKfe2OSaTK4brGliOqoQAhNOFnf0UuN/gky7iyAO49tQ+ZMql1JKeZqBJq5OuXOXmP6X5ySp"
            "l/PuLCqabbNN2HoLme+WfNuWipRGZ3caOFPrgschuCsZxZX8cH8fQT3HAove+CQh+Gzp/+A7ua6w2hrDnjPInmW0WWtQg8w/nykL"
            "JqD2F+WlqnWiZN4he4knHtXlrO9bV6xG5j7zlfLH0L6v/I6qpuvJPHChwyIGiW5Wmql5sYbMEq2/giLRRqln8qXhBmRuTD/34ggK"
            "41NJzLm2mcyHdj/lPYikf7yyf+hjSOah2lDTYBTU1dDWxWNJjXcmmn872r29UWntVRUyszT8BB3Q8mrL6fzCjf9tXbCMhUf/PhdL"
            "GX8t+SuHoGWfZvSkZSkzctFi74To8y8yHqZlmzEup2X9FqStoMVSGP1oOeqMPLTs5sW01xgjaFlWjKtpsSEB2irGDFrOTkZtWvYi"
            "xnZ+2pu0rGhGO0YZxnE+ur0axlzGPYx6tBxBxi+LaO8yHmd0pmXLM/5ZSFvPWMi4n9GIUYzx5wJagpZ1mtGTUZmRi/HdfNpLjKG0"
            "7G3L6IwzStNifIyj4vR42xlfiDPXiTFLnLlejLtoMTtGXabeWkZ+pt7YUtpOWlY1421aLIcxlpazm9GeqQeMsky9xYwTYrSfabFa"
            "xjJaTi5jHC17D6Mjox5TX45RiKk/JUr7lZbzivEu4zla9nHGYFqWM+NmRnmmHWHGPyJ0/W+MdYz3adkFjPGM+2hZroyGtNgGRlFG"
            "jGnnO71+Oa8ZH9KyixhPMYbQstwZ/7P+/9dhJSrJDeqWK32lM3nJ/6OY9gYBUVjz2rsiChMkM3uhqtUqGPIQ5O1aQb0XsGRXMRnY"
            "M3T1pMSrXpzMbonv5aGu71GfZ682Wc6a2W6lBG0mafHtLdR7gOWToKgKQXc7r9dEqlPtPbm/RAN0hXXQt9l6VHnPjzEtILYcVhlw"
            "p8pZKZIfcOAx1NRZ0G5J5a1u5QDxqvKH/AuWUvlBnYUeHO1o08q/akLmjrZBjj5IvffIjffYTGbPUnElA+g+aSi4Kc2YKs8xKDKE"
            "aaFT8tadVPbcGCxkDBONC2oe11P1sS/5sSaw/3xn66oWLTLnqzcMm4IIr7+dfxJVzr7Ns8MM6i96v3A8rEPlKtZ7cxgK0m58KEj1"
            "x7kXZmIBevLu6aBuRLXf/uChJVRW8cf6WKym2jMJP2sFF8QLRdN2SFPns85ZWMMaWcfzHtep96hA6JN5NuAwXRozVkm99/JXdz22"
            "AVORki2uNtT+jx206NA2+BhsJSP2azmZE8dVFW3hrkfT2y8//45f3v2HLcQuW1fxTJbcD2KlZ48X2EFTX/fVrJ3U9asPvONkD5dX"
            "KpyR7qHGwxrtFHQA9lfFk78NVan+bwrUOEDVREirzXJqPlbNrGhH2FmuVlAzSd0/bN9ebSdo+eqjgAVrUu/pyuIhJ/AuXSDRdoMa"
            "LwdvvuYM11n1rZZJ1P3skBbwc4GVLmtaju3TpcYfYbzcFSBAx2nZCmo+nDT2O1dYO6VU6xr+E6f+PT487QY7FeUOEL/XU+M9PGLk"
            "DvId68/OaFHv9fpklRl3uCMhrq2hSl3/oGV773lAUMwqhwFTOTK/V3fS9ISyovWed0uo8df/OpzqCUK9SXPtPan+Ljlm93mC2dAN"
            "y25dar6O4eXmXqDVv0io6im1r/nu1HHJC44KsFNK8vWp+9c7Z643yDnPeeCcRD3/9zfJenlD0bVqyZ42Jep7QndruTc8PywgG/ib"
            "mq/s5N6lPnDUNCMgIIMqZxUvPeADincGktLVzanr+Yb1xge8uSX+vdjNovK9HRt8YcMKbe64Cer6mdgmxfvC9OoLc398oJ4fzcsP"
            "v/nC3nw7s1ou6v7J3v2i7wd8FrwiQcPUvkcsjP+cH2gN7PJyWkvNl73zrYIjGuVp0tUr20S+9xOTeuodkNFptbAqNWpfo7hsbogD"
            "+rinZ4Qz+Icgx3dCQswBHWWPOtudp/Y1Hc4qhD1SOJGTpLGW2mdg/Fs87FH96UA2u4Eqz5f1nGOPAsJb/7jbkvtzrH71gQt2iJC5"
            "Ou38VJbMQTEnt9gh1tv+VM5vFtX/0/weW2QX4RZYIEftw1iBZUm26KzpputKrvPI7Dn0UtUWWS+8nZhUJkn1963t/TYkv87XdeVp"
            "Kgvc6g/bhr4NzBtxu2BG5tJfXJLbUD7uJP52vTaZOdOilTYonF992Gg2tW+yOiq33QYZV6OwyHX6VPtN+HwbJNWvWCf3YT41v3yL"
            "69aoRFFzZ4jcOmr8up7W1mjtEq2OwCV/x2cVPGyFDKQwB1M/an6KqlEZVoh3pdKZY4Y61HwSknErdMHij2xaNZU5gYbIEh01n8+v"
            "+pS6Pp43fbkt0bDQGUvDXZpUf4nRWy3QP7m8lvsSZaj2fQrObkXXuMbWC8dR+0J2xOM2c6TvfrGndYDa5+UrtkiZo3pvzTejI1T/"
            "nJaRADN0ahSTet1F9Ze/VPDWFiTr5PsoE99K1beVnzBFsZH9JY3HcDJLrjBimaJSsXnizn+o+XC+ux83QRdGeq8Uq1LzlZw6UG+M"
            "vG0fdXPqtKjxZpwWMUYBFQXIYlCdak+72N0Izao+nijRs5oq93l03hCV/ditIKlCXU/JtPpuA8Rj8l4g2NGEat/0q7IBmp+Y7LSk"
            "ihqf5MLx0M1oYGjxyE1Zat/sKbqwUh+d320quPcONR527gpeffTVJ6zUw/Zv+5qK1npo6ZWtAfunBsnnEduil85C1zYfPleyVPbv"
            "+AsfA5p1Ztbc5Fpqn86qq7DQRTkl3W6ypVT/rPT2Zhxx2yz2aSuk+sNyJ//RRj4pUxfnsKjrix0RGdVCSodCWR3xVH1O/sZjmig3"
            "5VLSyTZqPpiDsagGstNZs1HalFovnGa3IjW0zLFwdbsedb+w0r0qquhNx2o85OpCavwicZXKqK2xwmNxIPU8cnQzLJWQ7ArB9Kxk"
            "oM4/YY02ouaWPewVP4WozB3UJI9q3H9Y3+SjvhMwq5Oj6xB3yJoZp2PUesSIIlEZxOqvqgpYRN0/dtSDjWuQd0XD/d8D1HzY8rWW"
            "q1DEjzrBz7v+ro/+e+0SaMcNewHVg9T9xwTe8Iui31nK685XU98R2JpvlovRYqF78ypjBqjrOfF9JTfKss9oW/iI+i7Arg3NjDx+"
            "zr1/QZPt1v/7e5k81FQmL+uI9MG9V/ez1nll417sg7pZ5HeqG4/LtujEYCL2aOB34c19EPjy4FKJokRif6xwQ6lTH/jdCTn/aV8C"
            "/nGkbV1AUB+sxW9+ak86RbzIDhEzPNYHMzG3zB7HeeHRg1XVunl9oOalJHbIJAnnPzG+y7GsD+Z7tW7ZcCEDHzXeuz65tg+CLT+J"
            "tK5IxAtfNyh3f+4Dm7BnMqKbyC1tw58b/pN9EFZu8bQnO4CwdhGsnyXUD1rZBloCz9KIWqVdnHK5fnhevOv2kjJrokPh8vUs/X7I"
            "U+/PQhtTCOvTxS8ynPuB92rvg39YUXiYdTh+f28/hMQ3PdBLjCR+JpzSHI/vhwD+9NdSAklESM2eXy5F/fBlh2mYuctpvNGVK6bj"
            "UT9wj2xQi9uWSVx5sEPpWGM/4L6FWOCsPHz5h6nVVj39cPJe2OyM9iTi3Snv49rzBiA1ZktkyPMEPK01PMl05QD0FKemRlyOwjW9"
            "QwJDNQdg79zndyNKM3G4cMvyX+sBOD809NiuIh5vO/LJzzBgAD78YGWqlEfhkT7Dne0xAxC+CE5tMs8iOj+uHM7NGwA7wZIb3wXj"
            "8MQPzfVH7w9Akbjmu9b5esSCOV8uxL4ZgEa9Flvj2Ym4/Ubdyze6ByBa6q0hf3UwLnxPaf6feYPwJUrpzT9DcbjSe/OpoFWDcIRL"
            "7HRXTjw+I+J7iwcfhGIn9ZhVMil4/7lkj2f2gyBrZOHa63qSqLm8SeNi8CB0/tRHPzelEf7v5+6+fmoQCK5MPOFsHjF67qtqy8VB"
            "+DTs9U79Swjx9ZJQpULlIFSuc9MYm8kjVqsKml/4OAiP8voW8zbH4xLsa1yGE4MwOG4/LlWfTshtGF01X2QIDiUrSuwcdCfSL1l9"
            "GFYagozDHp/bnkcSCie8PHkshqCO/ZsrNNsEd8CW9+j9MwQH4n1fm6Xm4PV4RVlh3BD0eSfeLarYh39saOqTKxoC+8evB71rMnEZ"
            "OfW3zWgIPul330jfHI4vapvOvNU6BCqH/iFaujPwi/K5B26ND8FnB6c3vLdTCX3/usJmkWHoTSnfGXvgDBFlmWu/XnUYruE3lz8O"
            "ZRP8yW7V562HIetrz++cHQlEs0yZuvEesjxl+Sx58j/49PP0RsGEYehanuXSeTYKX2dr0sZ9lSw3NpprrpyG3zNyil/7chgK43ZG"
            "LjPDcZNVJcJ7uobB7RtbcfxCNs7beuBB59wRMP5on63/KYWItdtUGrFmBNLusCIqolMIycpaVaPNI6B8IjcENzlFSK+2i9L0HgEV"
            "CadjvHeziX2XzRvtIkfAV3fU4LqmJ/5K+6h/Xv4I2PneElJtyyZQ84IQQc4ILFwws93+xF5io7gffqt9BK4cx3dsehxAxKRaj4fP"
            "jMAIX5w0P36c2O/R/T1k5Shkhh6PMw6MJPZHFptkwShov/Xb9eFSIvFyu779L49RaNit5OC0JpEAt4+WO9mjIC8ye/59/wz82Kxf"
            "+5YUjMLGTK7eg8IxhHKF4qyeilF4u1XktbngOdzbok598NMoRBwWfjjbLQgXFNe1leEaA7n03d5xR5IJoX/NM09Ij0GTsnDjcvNc"
            "ouS5lJG48RhMvtIrinl3nOhJNsj+sGMMHo40Zo9VnSMy/eM/PI8fg01lRwafpGbiLfly+l+vjcFaszj7/h9p+CmDMhHlujG48vmH"
            "svvbIEL9oHDm9f4x2JX+uVCoNhavmkla4LJkHKSkHTccfpdLfH32qlRDYxweRZRFPvfYTvDbvKgxcB4Hrb7itCNmBwgri4/nosLH"
            "oT522REXsVziIXd1UH/+OCh/+zepfF8SkdhXFJX0dBweDwSXGh05gktJfV7q830cAs2/Hapecwj3++oW5r9wApTfSriZOqUQKgpb"
            "urMVJ+Cqemu4q2Ia7iate2uO3QR06iW0BG7MJRxvKwrlHZ6AKp9n1RE12TiaPmwXkDcBStOjfC8nEvHQwQYUUDkB9bu6qlWTzxAl"
            "Dc6Z575PQGStm+qrgnTc/27COm6+SVjzhW0+/DGbmBS2vF+oMgncTTGK7mxvYpPT14S9TpPweffDR+3BOYSx++TAgaOTsOmabYSl"
            "YwixZV6BYmnxJGxYZ8vXMJVHvKkwS1xROwkxeQqh9TpROO+KJpcnA5OwNycAqqfziByb2LbspVPk96LVCT+BSDy0fsbjKmsK5ldF"
            "d2gYZuNmrx029G+fIteXyczW48l4Wde81N1npsDAlW1CXAvGdyb+bpW8NwUtpj9e18wJwScq3ewWtE/B3tyobdrvE4gjJ7i3KHBP"
            "Q07o4c0aRA4xcGIRz7GN03AwNjc4zCSXOHZ+slXMcRrmabg0ze6JwjOiX4p8Zk/D9/aekxUrkohY5ZY53y5Pg3LZ7p2YVA7ueWfW"
            "4KqGaXgi1nfIoTkZ98gOU0mfmgYXMzHLV8VJxLqC4SVGa/9A2pLQSJm76cQInOzaYPUHztReZp/Ii8ajzZ9PWof+gc6EhdWr3ybj"
            "zYnnC2+c/wMpsjmiUjl5RP/20womdX/gVMniO4MpOYSMs1fvsok/UHr3fNzQ81w8/WGAxnrpGdh8ehEqLkjBWYaBLgesZiC+4L1C"
            "Z0MmvuRxTsl02Azwqs2rF3yUS7xPzIusuDgDK1KKB7eZHMP7g8+sf9IwA12H/dL2//LG/wfRW46S"
        )
    ),
    dtype="<f8",
)
_RECIPROCALS_1, _LOGS_1 = _SCALAR_TABLES[:33], _SCALAR_TABLES[33:99].reshape(33, 2)
_RECIPROCALS_2, _LOGS_2 = _SCALAR_TABLES[99:132], _SCALAR_TABLES[132:198].reshape(33, 2)
_RECIPROCALS_3, _LOGS_3 = _SCALAR_TABLES[198:327], _SCALAR_TABLES[327:585].reshape(129, 2)
_EXP2_128THS = _SCALAR_TABLES[585:841].reshape(128, 2)
# log2(1 + r' ln 2) - r' over r' (r' below, `_scalar_power`), and 2^t - 1 over t: highest first.
_SCALAR_LOG_COEFFICIENTS = hex_table(
    "-0x1.550472a9012d8p-4", "0x1.47fd462b6dee1p-3", "-0x1.62e4346694107p-2", "0x1.9c3a6966457e8p-24"
)
_SCALAR_EXP2_COEFFICIENTS = hex_table(
    "0x1.5d87fe78a6731p-10", "0x1.3b2ab6fba4e77p-7", "0x1.c6b08d704a0c0p-5", "0x1.ebfbdff82c58fp-3",
    "0x1.62e42fefa39efp-1",
)  # fmt: skip
_LOG2E_HIGH = float.fromhex("0x1.7154740000000p+0")
_SPLITTER = float.fromhex("0x1.0000002000000p+27")  # Dekker's 2^27 + 1
_128THS_SHIFTER = float.fromhex("0x1.8p+45")
_DEFAULT_NAN = np.array(0xFFF8000000000000, dtype=np.uint64).view(np.float64)  # SSE's 0 / 0


def _main_path(x: FloatArray, y: float) -> tuple[FloatArray, FloatArray]:
    """Return `__svml_pow8_ha`'s main path value of x ** y for positive finite x, and W = y log2 x."""
    fma = _fused_multiply_add
    y_array = np.full_like(x, y)

    def pair(a: float, b: float, t: FloatArray) -> FloatArray:
        return fma(t, np.full_like(t, a), np.full_like(t, b))

    # log2 x, as high + low.
    mantissa, exponent_plus_one = np.frexp(x)  # vgetmantpd [1/2, 1), vgetexppd + 1
    r = np.round(rcp14(mantissa) * 32) / 32
    e = np.where(r < 1.5, exponent_plus_one, exponent_plus_one - 1).astype(np.float64)
    index = (r.view(np.int64) >> 47) & 31  # r's top 5 fraction bits (r = 2 gives 0)
    u = fma(mantissa * 0.5, r, np.full_like(x, -0.5))
    u2 = u * u
    first, second, third, fourth, fifth = (pair(a, b, u) for a, b in _LOG_PAIRS)
    low = fma(u2 * u2, fma(u2, first, second), fma(u2, third, fourth))
    low = fma(u, fma(u2, low, fifth), _LOG_LO[index])
    table_and_exponent = _LOG_HI[index] + e
    linear = np.full_like(x, _TWO_OVER_LN2)
    head = fma(linear, u, table_and_exponent)  # e + T + (2 / ln 2) u
    term = head - table_and_exponent
    high = fma(-u, term, head)  # minus the square term
    term_error = fma(u, linear, -term)
    square_error = fma(term, u, -(head - high))
    log_low = low + (fma(-term_error, u, term_error) - square_error)
    log_high = high + log_low
    log_low = log_low - (log_high - high)
    # W = y log2 x, rounded toward zero, as product + its low part.
    product = multiply_toward_zero(log_high, y_array)
    product_low = fused_multiply_add_toward_zero(y_array, log_low, fma(y_array, log_high, -product))
    w = add_toward_zero(product, product_low)
    shifted = add_downward(w, np.full_like(x, SIXTEENTHS_SHIFTER))
    f = add_downward(w, -np.floor(w * 16) / 16) + (
        product_low - (w - product)
    )  # vreducepd, then W's low part
    # 2^W = 2^n 2^(j/16) 2^f.
    bits = shifted.view(np.int64)
    j = bits & 15
    scale = ((bits << 48) & _EXPONENT_MASK).view(np.float64)
    f2 = f * f
    first, second, third = (pair(a, b, f) for a, b in _EXP2_PAIRS)
    polynomial = fma(f, fma(f2, fma(f2, first, second), third), EXP2_16THS_LO[j])
    with np.errstate(over="ignore"):  # lanes off the main path only
        return fma(EXP2_16THS_HI[j], polynomial, EXP2_16THS_HI[j]) * scale, w


def _high_word(x: FloatArray) -> npt.NDArray[np.int64]:
    return x.view(np.int64) >> 32


def _biased_exponent(x: FloatArray) -> npt.NDArray[np.int64]:
    return (x.view(np.int64) >> 52) & 0x7FF


def _split(x: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return Dekker's split of x: a high part of 26 bits and the rest."""
    scaled = x * _SPLITTER
    high = scaled - (scaled - x)
    return high, x - high


def _scalar_power(x: FloatArray, y: float) -> FloatArray:
    """Return the scalar path's x ** y for positive finite x and a finite nonzero y, its operations in its order."""
    subnormal = x < 2.0**-1022
    x = np.where(subnormal, x * 2.0**200, x)
    k = ((_high_word(x) - 0x3FE7C000) >> 20) - np.where(subnormal, 200, 0)  # x = 2^k m', m' in [0.742, 1.484)
    m = ((x.view(np.int64) & 0xFFFFFFFFFFFFF) | 0x3FF0000000000000).view(np.float64)  # in [1, 2)
    # log2 x = k + log2 m: m r1 r2 r3 is near log2 e (the third table's reciprocals are times log2 e), each r
    # from its table by the leading bits of the product so far; log2 m = -log2(r1 r2 r3 / log2 e) (the tables'
    # logs, high + low) + log2(1 + r' ln 2), r' = m r1 r2 r3 - log2 e (high part): r' plus a polynomial.
    i1 = ((_high_word(m) & 0xFC000) + 0x4000) >> 15
    product = _RECIPROCALS_1[i1] * m
    log_high = k.astype(np.float64) + _LOGS_1[i1, 0]
    i2 = ((_high_word(product) & 0xFC00) + 0x400) >> 11
    product = product * _RECIPROCALS_2[i2]
    reciprocal = _RECIPROCALS_1[i1] * _RECIPROCALS_2[i2]
    log_high = log_high + _LOGS_2[i2, 0]
    i3 = ((_high_word(product) & 0xFF0) + 0x10) >> 5
    reciprocal = reciprocal * _RECIPROCALS_3[i3]
    log_high = log_high + _LOGS_3[i3, 0]
    product = product * _RECIPROCALS_3[i3]
    r = product - _LOG2E_HIGH
    (m_high, m_low), (reciprocal_high, reciprocal_low) = _split(m), _split(reciprocal)
    product_error = m_high * reciprocal_high - product
    for term in (reciprocal_high * m_low, m_high * reciprocal_low, m_low * reciprocal_low):
        product_error = product_error + term
    log_sum = log_high + r
    log_sum_low = (log_high - log_sum) + r
    r = r + product_error
    polynomial = _SCALAR_LOG_COEFFICIENTS[0] * r
    for coefficient in _SCALAR_LOG_COEFFICIENTS[1:]:
        polynomial = (polynomial + coefficient) * r
    low = (_LOGS_1[i1, 1] + (_LOGS_2[i2, 1] + _LOGS_3[i3, 1])) + (product_error + log_sum_low)
    with_polynomial = log_sum + polynomial
    with_polynomial_low = (log_sum - with_polynomial) + polynomial
    log2_x = low + with_polynomial
    log2_x_low = ((with_polynomial - log2_x) + low) + with_polynomial_low
    # y log2 x = N / 128 + t, N an integer, from the split product.
    (log2_x_high, log2_x_rest), (y_high, y_low) = _split(log2_x), _split(np.full_like(x, y))
    product_high = y_high * log2_x_high
    shifted = product_high + _128THS_SHIFTER
    product_low = y_high * log2_x_rest + log2_x_rest * y_low
    product_low = product_low + log2_x_high * y_low
    product_low = product_low + log2_x_low * y
    t = (product_high - (shifted - _128THS_SHIFTER)) + product_low
    count = ((shifted.view(np.int64) & 0xFFFFFFFF) ^ 0x80000000) - 0x80000000  # N, a signed 32-bit word
    j, n = count & 127, count >> 7
    polynomial = _SCALAR_EXP2_COEFFICIENTS[0] * t
    for coefficient in _SCALAR_EXP2_COEFFICIENTS[1:]:
        polynomial = (polynomial + coefficient) * t
    table_high, table_low = _EXP2_128THS[j, 0], _EXP2_128THS[j, 1]
    tail = polynomial * table_high + table_low
    significand = tail + table_high  # 2^(j/128 + t), near [1, 2)
    exponent = n + _biased_exponent(significand) - 0x3FF
    bits = (significand.view(np.int64) & ~_EXPONENT_MASK) | (((exponent + 0x3FF) & 0x7FF) << 52)
    # Below 2^-1022: formed 2^200 larger, then scaled down; as a split double-double down to 2^-1031.
    scale = (((n + 0x3FF + 200) & 0x7FF) << 52).view(np.float64)
    significand_high, significand_low = _split(significand)
    scaled = (significand_low + (tail + (table_high - significand))) * scale + significand_high * scale
    power = np.select(
        [exponent >= 0x400, exponent >= -0x3FE, exponent >= -0x408, exponent >= -0x43C],
        [
            np.full_like(x, np.inf),
            bits.view(np.float64),
            scaled * 2.0**-200,
            significand * scale * 2.0**-200,
        ],
        0.0,
    )
    # The exponents of log2 x (high part) and y decide first: |y log2 x| >= 2^11 overflows or underflows, below
    # 2^-60 it rounds to 1.
    exponents = _biased_exponent(log_sum) + int(_biased_exponent(np.array(y)))
    overflow = np.where(np.signbit(log_sum) == (y < 0), np.inf, 0.0)
    return np.where(exponents >= 0x809, overflow, np.where(exponents <= 0x7C0, 1.0, power))


def _scalar_path(x: FloatArray, y: float) -> FloatArray:
    """Return `__svml_dpow_ha_cout_rare_internal`'s x ** y: plain SSE2 operations rounded to nearest one by one
    on |x|, the sign for odd integer y; its special cases in its order."""
    integer = bool(np.isfinite(y)) and y.is_integer()
    odd = integer and abs(y) < 2.0**53 and int(y) % 2 == 1
    sign = np.where(np.signbit(x) & odd, -1.0, 1.0)
    computed = np.ones_like(x)  # the other lanes and exponents are special cases below
    computing = np.isfinite(x) & (x != 0) & (np.abs(x) != 1)
    if np.isfinite(y) and y != 0 and computing.any():
        with np.errstate(all="ignore"):  # lanes that over- or underflow compute values they do not take
            computed = sign * _scalar_power(np.where(computing, np.abs(x), 2.0), y)
    minus_one = (-1.0 if odd else 1.0) if integer or np.isinf(y) else _DEFAULT_NAN
    zero = sign * (np.inf if np.signbit(y) else 0.0)  # sign / (x * x) or sign (x * x)
    return np.select(
        [
            (x == 1) | (y == 0),
            np.isnan(x) | np.isnan(y),
            x == 0,
            x == -1,
            np.isinf(x) | np.isinf(y),
            (x < 0) & (not integer),
        ],
        [
            np.ones_like(x),
            np.where(np.isnan(x), x * 1.0, y * 1.0),  # the first NaN operand, quieted (SSE's x + y)
            zero,
            np.full_like(x, minus_one),
            sign * np.where((np.abs(x) < 1) == (y > 0), 0.0, np.inf),
            np.full_like(x, _DEFAULT_NAN),
        ],
        computed,
    )


def svml_power_emulated(base: npt.ArrayLike, exponent: float) -> FloatArray:
    """Return np.power(base, exponent) as numpy computes it on AVX-512 machines, from float64 operations only.

    `__svml_pow8_ha`'s main path for positive finite bases with |W| <= 1021.5, its scalar path for every other
    base, each in its order of operations (module docstring)."""
    x = np.asarray(base, dtype=np.float64)
    y = float(exponent)
    positive = (x > 0) & np.isfinite(x) & bool(np.isfinite(y))
    main, w = _main_path(np.where(positive, x, 1.0), y)
    main_path = positive & (np.abs(w) <= _MAIN_PATH_W)
    if main_path.all():
        return main
    return np.where(main_path, main, _scalar_path(np.where(main_path, 1.0, x), y))


# Bases whose tenth power SVML rounds other than the C library, with SVML's results: numpy is SVML here exactly
# when it gives these.
_SVML_PROBE_BASES = np.array([0.7771, 1.4142, 1.0106, 2.8012])
_SVML_PROBE_POWERS = hex_table(
    "0x1.48f308d97fb93p-4", "0x1.fff36e40df3c4p+4", "0x1.1c77b8bcf1314p+0", "0x1.d0cb73f450cb1p+14"
)
NUMPY_POWER_IS_SVML = bool(np.array_equal(np.power(_SVML_PROBE_BASES, 10.0), _SVML_PROBE_POWERS))


def power_avx512(base: npt.ArrayLike, exponent: float) -> FloatArray:
    """Return np.power(base, exponent) as the devkit computed it on the AVX-512 machines of the official
    results: numpy's own where numpy runs SVML (exact, and faster), the replay elsewhere."""
    if NUMPY_POWER_IS_SVML:
        return np.power(base, exponent)
    return svml_power_emulated(base, exponent)
