/* evtk._ckernels: the counting of fixed windows in compiled code that releases the GIL.
 *
 * Built at install where a C compiler is present (setup.py marks it optional); without it evtk counts
 * with numpy (evtk/_native.py chooses). The Python wrapper, evtk._native.count_windows, checks every
 * argument's type and shape; this file checks every index again before it touches memory, so that no
 * argument can make it read or write outside its buffers.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>

/* One window's events into its bins: the picked events i in [a, z) (event picks[i], or first + i without
 * picks), each to bin base + k (k = ky[y] + kx[x], plus on_step when ON) where 0 <= k < limit, else to dump.
 * The caller has checked that every pick, and every bin it can reach, lies inside its buffer. restrict: the
 * bins share no memory with the columns and tables, so the compiler may load the next events' columns while
 * a bin is being written (twice as fast as without), and nothing branches on the polarity. */
#define COUNT_WINDOW(NAME, BIN_T, UBIN_T)                                                                       \
    static int NAME(const uint16_t *restrict x, const uint16_t *restrict y, const uint8_t *restrict p,         \
                    const int64_t *restrict picks, Py_ssize_t n_ev, int64_t first, int64_t a, int64_t z,        \
                    const int64_t *restrict ky, const int64_t *restrict kx, int64_t on_step, int64_t limit,     \
                    int64_t base, int64_t dump, int net, BIN_T *restrict out)                                   \
    {                                                                                                          \
        for (int64_t i = a; i < z; i++) {                                                                      \
            int64_t e = picks ? picks[i] : first + i;                                                          \
            if (picks && (e < 0 || e >= n_ev))                                                                 \
                return -1;                                                                                     \
            int64_t on = p[e] != 0; /* arithmetic, no branch on it: polarities are as good as random */     \
            int64_t k = ky[y[e]] + kx[x[e]] + (on_step & -on);                                                 \
            int64_t bin = (uint64_t)k < (uint64_t)limit ? base + k : dump;                                     \
            out[bin] = (BIN_T)(UBIN_T)((UBIN_T)out[bin] + (UBIN_T)(1 - 2 * (net & (1 - on))));                \
        }                                                                                                      \
        return 0;                                                                                              \
    }

COUNT_WINDOW(count_window16, int16_t, uint16_t)
COUNT_WINDOW(count_window32, int32_t, uint32_t)

/* count_windows(x, y, p, picks, use_picks, first, at, ky, kx, on_step, limit, per_window, dump, net, out, width)
 *
 * For window w (0 <= w < len(at) - 1) and each of its picked events i in [at[w], at[w + 1]) (event
 * picks[i] with use_picks, else first + i), the bin of the event within its window is
 * k = ky[y] + kx[x] (+ on_step for an ON event); the bin is w * per_window + k where 0 <= k < limit, else
 * the dump bin. That bin of out (int16 bins with width 2, int32 with width 4) gets +1, or with net the
 * event's sign (+1 ON, -1 OFF). x and y are uint16, p uint8 (not 0: ON), picks, at, ky and kx int64;
 * ky and kx have 65536 entries (every uint16 coordinate). Adds wrap in the bins' type (the caller
 * chooses a type that holds every window's events).
 *
 * Returns None; raises ValueError for an argument this file refuses (the wrapper's checks make that a
 * bug), after which out may hold part of the counts.
 */
static PyObject *
count_windows(PyObject *self, PyObject *args)
{
    Py_buffer xb, yb, pb, pickb, atb, kyb, kxb, outb;
    int use_picks, net, width;
    Py_ssize_t first;
    long long on_step, limit, per_window, dump;
    const char *fault = NULL;

    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*pny*y*y*LLLLpw*i", &xb, &yb, &pb, &pickb, &use_picks, &first, &atb,
                          &kyb, &kxb, &on_step, &limit, &per_window, &dump, &net, &outb, &width))
        return NULL;

    const uint16_t *x = (const uint16_t *)xb.buf, *y = (const uint16_t *)yb.buf;
    const uint8_t *p = (const uint8_t *)pb.buf;
    const int64_t *picks = use_picks ? (const int64_t *)pickb.buf : NULL, *at = (const int64_t *)atb.buf;
    const int64_t *ky = (const int64_t *)kyb.buf, *kx = (const int64_t *)kxb.buf;
    Py_ssize_t n_ev = xb.len / 2, n_picks = pickb.len / 8, n_at = atb.len / 8;
    Py_ssize_t n_out = width == 2 ? outb.len / 2 : outb.len / 4;

    if (yb.len / 2 != n_ev || pb.len != n_ev)
        fault = "x, y and p differ in length";
    else if (kyb.len != 65536 * 8 || kxb.len != 65536 * 8)
        fault = "the tables need 65536 int64 entries";
    else if (width != 2 && width != 4)
        fault = "bins are 2 or 4 bytes";
    else if (dump < 0 || dump >= n_out || limit < 0 || per_window < 0 || limit > per_window || first < 0)
        fault = "a bin, limit or offset outside the bins";
    if (fault == NULL) {
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t w = 0; w + 1 < n_at; w++) {
            int64_t a = at[w], z = at[w + 1];
            int64_t base = (int64_t)w * per_window;
            if (a < 0 || z < a || (use_picks ? z > n_picks : z > n_ev - first)) {
                fault = "a window's events outside the picks";
                break;
            }
            if (base + limit > n_out) {
                fault = "a window's bins outside the bins";
                break;
            }
            int bad = width == 2
                ? count_window16(x, y, p, picks, n_ev, first, a, z, ky, kx, on_step, limit, base, dump, net,
                                 (int16_t *)outb.buf)
                : count_window32(x, y, p, picks, n_ev, first, a, z, ky, kx, on_step, limit, base, dump, net,
                                 (int32_t *)outb.buf);
            if (bad) {
                fault = "a pick outside the events";
                break;
            }
        }
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&xb);
    PyBuffer_Release(&yb);
    PyBuffer_Release(&pb);
    PyBuffer_Release(&pickb);
    PyBuffer_Release(&atb);
    PyBuffer_Release(&kyb);
    PyBuffer_Release(&kxb);
    PyBuffer_Release(&outb);
    if (fault != NULL) {
        PyErr_SetString(PyExc_ValueError, fault);
        return NULL;
    }
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"count_windows", count_windows, METH_VARARGS,
     "Count events into their windows' bins with the GIL released (see evtk._native.count_windows)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_ckernels", "evtk's compiled counting kernels (optional).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC
PyInit__ckernels(void)
{
    return PyModule_Create(&module);
}
