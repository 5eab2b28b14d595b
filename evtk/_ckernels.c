/* evtk._ckernels: the counting of fixed windows, and the AEDAT4 reader's batches of LZ4 event packets, in
 * compiled code that releases the GIL.
 *
 * Built at install where a C compiler is present (setup.py marks it optional); without it evtk counts
 * with numpy and decodes in Python (evtk/_native.py chooses). The Python wrappers, evtk._native.count_windows
 * and evtk._native.decode_lz4_batch, check every argument's type and shape; this file checks every index
 * again before it touches memory, so that no argument and no byte of a file can make it read or write
 * outside its buffers.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

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
            uint64_t on = p[e] != 0; /* arithmetic, no branch on it: polarities are as good as random */    \
            /* unsigned: any table values wrap (defined), and one compare finds 0 <= k < limit */              \
            uint64_t k = (uint64_t)ky[y[e]] + (uint64_t)kx[x[e]] + ((uint64_t)on_step & (0 - on));             \
            int64_t bin = k < (uint64_t)limit ? base + (int64_t)k : dump;                                      \
            out[bin] = (BIN_T)(UBIN_T)((UBIN_T)out[bin] + (UBIN_T)(1 - 2 * (int64_t)(net & (1 - on))));       \
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
            if (a < 0 || z < a || (use_picks ? z > n_picks : z > n_ev - first)) {
                fault = "a window's events outside the picks";
                break;
            }
            /* w * per_window + limit <= n_out, checked without computing a product that could overflow */
            if (limit > n_out || (per_window > 0 && w > (n_out - limit) / per_window)) {
                fault = "a window's bins outside the bins";
                break;
            }
            int64_t base = (int64_t)w * per_window;
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

/* ---- the AEDAT4 reader's batches of LZ4 event packets ---------------------------------------------------- */

typedef size_t (*lz4f_decompress_fn)(void *ctx, void *dst, size_t *dst_size, const void *src, size_t *src_size,
                                     const void *options);
typedef unsigned (*lz4f_is_error_fn)(size_t code);
typedef void (*lz4f_reset_fn)(void *ctx);

static inline uint32_t
rd_u32(const uint8_t *b) { uint32_t v; memcpy(&v, b, 4); return v; }  /* little-endian hosts (checked at import) */
static inline int32_t
rd_i32(const uint8_t *b) { int32_t v; memcpy(&v, b, 4); return v; }
static inline uint16_t
rd_u16(const uint8_t *b) { uint16_t v; memcpy(&v, b, 2); return v; }

/* The vector in field 0 of the root table of the FlatBuffer b[0:n] with identifier ident, of 16-byte structs
 * that end the buffer: evtk.io._fbpy._root_vector_at's checks, every one (its start and length into *start,
 * *count; -1 where a check fails). */
static int
root_vector(const uint8_t *b, int64_t n, const char *ident, int64_t *start, int64_t *count)
{
    int64_t root;
    if (n >= 12 && memcmp(b + 8, ident, 4) == 0)
        root = 4 + (int64_t)rd_u32(b + 4);
    else if (n >= 8 && memcmp(b + 4, ident, 4) == 0)
        root = (int64_t)rd_u32(b);
    else
        return -1;
    if (root + 4 > n)
        return -1;
    int64_t vt = root - (int64_t)rd_i32(b + root);
    if (vt < 0 || vt + 4 > n)
        return -1;
    int64_t vt_size = rd_u16(b + vt), tb_size = rd_u16(b + vt + 2);
    if (vt_size < 4 || vt + vt_size > n || root + tb_size > n)
        return -1;
    int64_t off = vt_size >= 6 ? rd_u16(b + vt + 4) : 0;
    if (off == 0) {
        *start = *count = 0;
    } else {
        int64_t field = root + off;
        if (off + 1 > tb_size || field + 4 > n)
            return -1;
        int64_t v = field + (int64_t)rd_u32(b + field);
        if (v + 4 > n)
            return -1;
        *count = (int64_t)rd_u32(b + v);
        if (v + 4 + *count * 16 > n)
            return -1;
        *start = v + 4;
    }
    if (n - (*start + 16 * *count) >= 16)  /* room for another event after the vector: a length that shrank */
        return -1;
    return 0;
}

/* One LZ4 frame src[0:n] into dst (at most room bytes): evtk.io._compression.lz4_into_at's rule (the stated
 * content size within room, the frame whole, the size met). Returns the bytes written, or -1. */
static int64_t
lz4_frame(const uint8_t *src, int64_t n, uint8_t *dst, int64_t room, int verify, lz4f_decompress_fn dec,
          lz4f_is_error_fn is_error, lz4f_reset_fn reset, void *ctx)
{
    static const uint8_t magic[4] = {0x04, 0x22, 0x4d, 0x18};
    if (n < 6 || memcmp(src, magic, 4) != 0)
        return -1;
    uint8_t flg = src[4];
    if (!verify && n > 6 && (flg & 0x14))
        return -1;  /* checksums to leave unread: the Python route rebuilds the frame without them */
    int64_t size = 0;
    if (n >= 15 && (flg & 0x08)) {
        uint64_t stated;
        memcpy(&stated, src + 6, 8);
        if (stated > (uint64_t)room)
            return -1;
        size = (int64_t)stated;
    }
    int64_t written = 0, read = 0;
    int ended = 0;
    for (;;) {
        size_t dst_n = (size_t)(room - written), src_n = (size_t)(n - read);
        size_t hint = dec(ctx, dst + written, &dst_n, src + read, &src_n, NULL);
        if (is_error(hint)) {
            reset(ctx);
            return -1;
        }
        written += (int64_t)dst_n;
        read += (int64_t)src_n;
        if (hint == 0) {
            ended = 1;
            break;
        }
        if (dst_n == 0 && src_n == 0)
            break;
    }
    if (!ended || (size > 0 && written != size)) {
        reset(ctx);
        return -1;
    }
    return written;
}

/* decode_lz4_batch(raw, heads, sids, sizes, counts, verify, decompress, is_error, reset, ctx, stage, floor, ratio,
 *                  most, t, x, y, p, width, height)
 *
 * The event packets of one batch of the AEDAT4 reader, each an LZ4 frame: packet j's 8-byte header (stream id
 * and body size, int32) at raw[heads[j]], then its body, which must match sids[j] and sizes[j]; decompressed into
 * stage (at most min(most, floor + ratio * size) bytes), the FlatBuffer's EVTS vector of counts[j] events split
 * into the columns t, x, y, p after the previous packet's (x and y within the sensor; a polarity byte not 0 is
 * ON: 1). decompress, is_error, reset and ctx: LZ4F_decompress, LZ4F_isError, LZ4F_resetDecompressionContext
 * and a decompression context of this thread, as addresses. The GIL is released throughout.
 *
 * Returns True when every packet decoded; False at anything else (the caller decodes the batch again in Python,
 * which names the fault); the columns may then hold part of the batch.
 */
static PyObject *
decode_lz4_batch(PyObject *self, PyObject *args)
{
    Py_buffer rawb, headb, sidb, sizeb, countb, stageb, tb, xb, yb, pb;
    int verify;
    unsigned long long dec_at, err_at, reset_at, ctx_at;
    long long floor_bytes, ratio, most;
    int width, height;
    int ok = 1;

    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*pKKKKw*LLLw*w*w*w*ii", &rawb, &headb, &sidb, &sizeb, &countb, &verify,
                          &dec_at, &err_at, &reset_at, &ctx_at, &stageb, &floor_bytes, &ratio, &most, &tb, &xb, &yb,
                          &pb, &width, &height))
        return NULL;
    const uint8_t *raw = (const uint8_t *)rawb.buf;
    const int64_t *heads = (const int64_t *)headb.buf, *sids = (const int64_t *)sidb.buf;
    const int64_t *sizes = (const int64_t *)sizeb.buf, *counts = (const int64_t *)countb.buf;
    uint8_t *stage = (uint8_t *)stageb.buf;
    int64_t *t = (int64_t *)tb.buf;
    uint16_t *x = (uint16_t *)xb.buf, *y = (uint16_t *)yb.buf;
    uint8_t *p = (uint8_t *)pb.buf;
    int64_t n_raw = rawb.len, n_pk = headb.len / 8, n_stage = stageb.len, n_out = tb.len / 8;
    lz4f_decompress_fn dec = (lz4f_decompress_fn)(uintptr_t)dec_at;
    lz4f_is_error_fn is_error = (lz4f_is_error_fn)(uintptr_t)err_at;
    lz4f_reset_fn reset = (lz4f_reset_fn)(uintptr_t)reset_at;
    void *ctx = (void *)(uintptr_t)ctx_at;

    if (sidb.len / 8 != n_pk || sizeb.len / 8 != n_pk || countb.len / 8 != n_pk || xb.len / 2 != n_out
        || yb.len / 2 != n_out || pb.len != n_out || !dec || !is_error || !reset || !ctx || width < 0 || height < 0
        || floor_bytes < 0 || ratio < 0 || most < 0)
        ok = 0;
    if (ok) {
        Py_BEGIN_ALLOW_THREADS
        int64_t cursor = 0;
        for (int64_t j = 0; j < n_pk && ok; j++) {
            int64_t h = heads[j];
            if (h < 0 || h > n_raw - 8) { ok = 0; break; }
            int64_t sid = rd_i32(raw + h), size = rd_i32(raw + h + 4);
            if (sid != sids[j] || size != sizes[j] || size < 0 || size > n_raw - 8 - h) { ok = 0; break; }
            /* min(most, floor + ratio * size), without computing a sum or product that could overflow */
            int64_t limit = most;
            if (ratio == 0 ? floor_bytes < most : (floor_bytes < most && size < (most - floor_bytes) / ratio))
                limit = floor_bytes + ratio * size;
            int64_t room = limit < n_stage ? limit : n_stage;
            int64_t n = lz4_frame(raw + h + 8, size, stage, room, verify, dec, is_error, reset, ctx);
            int64_t start, count;
            if (n < 0 || root_vector(stage, n, "EVTS", &start, &count) != 0 || count != counts[j]
                || count > n_out - cursor) { ok = 0; break; }
            const uint8_t *ev = stage + start;
            uint32_t most_x = 0, most_y = 0;
            for (int64_t i = 0; i < count; i++, ev += 16) {
                int64_t tt;
                uint16_t xx, yy;
                memcpy(&tt, ev, 8);
                memcpy(&xx, ev + 8, 2);
                memcpy(&yy, ev + 10, 2);
                t[cursor + i] = tt;
                x[cursor + i] = xx;
                y[cursor + i] = yy;
                p[cursor + i] = ev[12] != 0;
                most_x = xx > most_x ? xx : most_x;
                most_y = yy > most_y ? yy : most_y;
            }
            if (count > 0 && (most_x >= (uint32_t)width || most_y >= (uint32_t)height)) { ok = 0; break; }
            cursor += count;
        }
        if (ok && cursor != n_out)
            ok = 0;
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&rawb);
    PyBuffer_Release(&headb);
    PyBuffer_Release(&sidb);
    PyBuffer_Release(&sizeb);
    PyBuffer_Release(&countb);
    PyBuffer_Release(&stageb);
    PyBuffer_Release(&tb);
    PyBuffer_Release(&xb);
    PyBuffer_Release(&yb);
    PyBuffer_Release(&pb);
    return PyBool_FromLong(ok);
}

static PyMethodDef methods[] = {
    {"count_windows", count_windows, METH_VARARGS,
     "Count events into their windows' bins with the GIL released (see evtk._native.count_windows)."},
    {"decode_lz4_batch", decode_lz4_batch, METH_VARARGS,
     "Decode a batch of LZ4 event packets with the GIL released (see evtk._native.decode_lz4_batch)."},
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
