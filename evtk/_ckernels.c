/* evtk._ckernels: the counting of fixed windows and the sums of their net counts, the counting of a schedule's windows
 * with their ON-event times and the timing linearisation's solve, and the AEDAT4 reader's batches of
 * LZ4 (and, through the system's libzstd, Zstandard) event packets, in compiled code that releases the GIL.
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
#include <errno.h>
#include <math.h>
#ifndef _WIN32
#include <unistd.h>
#endif
#if defined(__SSE2__) || defined(_M_X64)
#include <emmintrin.h>
#define HAVE_SSE2 1
#endif

/* A hot loop compiled as a function of its own: inlined into its caller, it shares the registers with the
 * caller's values, and the compiler kept the loop's pointers on the stack, reloading them at every event or word
 * (the counting below, EVT 3.0's e3_fast and EVT 2.0's e2_decode: a fifth of their instructions). */
#if defined(__GNUC__) || defined(__clang__)
#define NOINLINE __attribute__((noinline))
#elif defined(_MSC_VER)
#define NOINLINE __declspec(noinline)
#else
#define NOINLINE
#endif

/* One window's events into its bins: the picked events i in [a, z) (event picks[i], or first + i without
 * picks), each to bin base + k (k = ky[y] + kx[x], plus on_step when ON) where 0 <= k < limit, else to dump.
 * The caller has checked that every pick, and every bin it can reach, lies inside its buffer. restrict: the
 * bins share no memory with the columns and tables, so the compiler may load the next events' columns while
 * a bin is being written (twice as fast as without), and nothing branches on the polarity. */
#define COUNT_WINDOW(NAME, BIN_T, UBIN_T)                                                                       \
    NOINLINE static int NAME(const uint16_t *restrict x, const uint16_t *restrict y, const uint8_t *restrict p, \
                             const int64_t *restrict picks, Py_ssize_t n_ev, int64_t first, int64_t a,          \
                             int64_t z, const int64_t *restrict ky, const int64_t *restrict kx,                 \
                             int64_t on_step, int64_t limit, int64_t base, int64_t dump, int net,               \
                             BIN_T *restrict out)                                                               \
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

/* count_windows(x, y, p, picks, use_picks, first, at, ky, kx, on_step, limit, per_window, dump, net, out, width
 *               [, zero_from, zero_to])
 *
 * For window w (0 <= w < len(at) - 1) and each of its picked events i in [at[w], at[w + 1]) (event
 * picks[i] with use_picks, else first + i), the bin of the event within its window is
 * k = ky[y] + kx[x] (+ on_step for an ON event); the bin is w * per_window + k where 0 <= k < limit, else
 * the dump bin. That bin of out (int16 bins with width 2, int32 with width 4) gets +1, or with net the
 * event's sign (+1 ON, -1 OFF). x and y are uint16, p uint8 (not 0: ON), picks, at, ky and kx int64;
 * ky and kx have 65536 entries (every uint16 coordinate). Adds wrap in the bins' type (the caller
 * chooses a type that holds every window's events). Windows zero_from <= w < zero_to have their per_window
 * bins set to 0 just before their events are counted (still in cache when the events reach them; a batch's
 * bins cleared at once ahead had left the cache by the time its later windows were counted).
 *
 * Returns None; raises ValueError for an argument this file refuses (the wrapper's checks make that a
 * bug), after which out may hold part of the counts.
 */
static PyObject *
count_windows(PyObject *self, PyObject *args)
{
    Py_buffer xb, yb, pb, pickb, atb, kyb, kxb, outb;
    int use_picks, net, width;
    Py_ssize_t first, zero_from = 0, zero_to = 0;
    long long on_step, limit, per_window, dump;
    const char *fault = NULL;

    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*pny*y*y*LLLLpw*i|nn", &xb, &yb, &pb, &pickb, &use_picks, &first, &atb,
                          &kyb, &kxb, &on_step, &limit, &per_window, &dump, &net, &outb, &width, &zero_from,
                          &zero_to))
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
            if (w >= zero_from && w < zero_to) {
                if (per_window > 0 && (per_window > n_out || w > (n_out - per_window) / per_window)) {
                    fault = "a window's bins outside the bins";
                    break;
                }
                memset((char *)outb.buf + base * width, 0, (size_t)per_window * (size_t)width);
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

/* ---- the sums of a batch of windows' net counts (evtk enob) ------------------------------------------- */

/* The least and the largest of v[0 .. w - 1] into *lo and *hi (which hold a running least and largest). Compiled
 * on its own: inlined into net_sums_rows, the loop was left scalar. */
#define VALUE_RANGE(NAME, T)                                                                                    \
    NOINLINE static void NAME(const T *restrict v, int64_t w, int64_t *lo, int64_t *hi)                        \
    {                                                                                                          \
        T l = 0, u = 0;                                                                                        \
        for (int64_t c = 0; c < w; c++) {                                                                      \
            l = v[c] < l ? v[c] : l;                                                                           \
            u = v[c] > u ? v[c] : u;                                                                           \
        }                                                                                                      \
        *lo = l < *lo ? l : *lo;                                                                               \
        *hi = u > *hi ? u : *hi;                                                                               \
    }

VALUE_RANGE(range16, int16_t)
VALUE_RANGE(range32, int32_t)

#ifdef HAVE_SSE2
/* Row `row` of k windows' int16 net counts with SSE2, eight pixels at a time and every window of them before the
 * next eight (their sums in registers): each pixel's sum and sum of squares over the windows into S1 and S2, two
 * windows' counts interleaved so that pmaddwd gives a * a + b * b (and with ones a + b) per pixel; where the eight
 * pixels' largest magnitude m lets the int32 sums overflow (k * m * m > INT32_MAX), they are summed again in 64
 * bits. With wsum (k rows of w / 2 int32, w even), each window's sums of pixel pairs (c, c + 1) are added to its
 * row: the block sums' first step. Returns the row's largest magnitude. */
NOINLINE static int64_t
row_sums16_sse2(const int16_t *restrict net, int64_t k, int64_t h, int64_t w, int64_t row, uint64_t *restrict S1,
                uint64_t *restrict S2, int32_t *restrict wsum)
{
    const int64_t plane = h * w, half = w / 2;
    const int16_t *top = net + row * w;
    const __m128i ones = _mm_set1_epi16(1), zero = _mm_setzero_si128();
    int64_t big = 0, c = 0;
    for (; c + 8 <= w; c += 8) {
        __m128i s1l = zero, s1h = zero, s2l = zero, s2h = zero, mn = zero, mx = zero;
        for (int64_t i = 0; i < k; i += 2) {
            __m128i a = _mm_loadu_si128((const __m128i *)(top + i * plane + c));
            __m128i b = i + 1 < k ? _mm_loadu_si128((const __m128i *)(top + (i + 1) * plane + c)) : zero;
            mn = _mm_min_epi16(mn, _mm_min_epi16(a, b));
            mx = _mm_max_epi16(mx, _mm_max_epi16(a, b));
            __m128i lo = _mm_unpacklo_epi16(a, b), hi = _mm_unpackhi_epi16(a, b);
            s1l = _mm_add_epi32(s1l, _mm_madd_epi16(lo, ones));
            s1h = _mm_add_epi32(s1h, _mm_madd_epi16(hi, ones));
            s2l = _mm_add_epi32(s2l, _mm_madd_epi16(lo, lo));
            s2h = _mm_add_epi32(s2h, _mm_madd_epi16(hi, hi));
            if (wsum != NULL) {
                __m128i *pa = (__m128i *)(wsum + i * half + c / 2);
                _mm_storeu_si128(pa, _mm_add_epi32(_mm_loadu_si128(pa), _mm_madd_epi16(a, ones)));
                if (i + 1 < k) {
                    __m128i *pb = (__m128i *)(wsum + (i + 1) * half + c / 2);
                    _mm_storeu_si128(pb, _mm_add_epi32(_mm_loadu_si128(pb), _mm_madd_epi16(b, ones)));
                }
            }
        }
        /* the eight pixels' least and largest counts across their lanes (two shifts and a compare each) */
        mn = _mm_min_epi16(mn, _mm_srli_si128(mn, 8));
        mn = _mm_min_epi16(mn, _mm_srli_si128(mn, 4));
        mn = _mm_min_epi16(mn, _mm_srli_si128(mn, 2));
        mx = _mm_max_epi16(mx, _mm_srli_si128(mx, 8));
        mx = _mm_max_epi16(mx, _mm_srli_si128(mx, 4));
        mx = _mm_max_epi16(mx, _mm_srli_si128(mx, 2));
        int64_t least = (int16_t)_mm_cvtsi128_si32(mn), most = (int16_t)_mm_cvtsi128_si32(mx);
        int64_t m = -least > most ? -least : most;
        big = m > big ? m : big;
        if (m <= 32767 && k <= INT32_MAX && (uint64_t)k * (uint64_t)(m * m) <= INT32_MAX) {  /* int32 sums exact */
            /* widened in registers: each sum's sign (S1) or zero (S2, squares) as its upper half */
            __m128i sl = _mm_srai_epi32(s1l, 31), sh = _mm_srai_epi32(s1h, 31);
            _mm_storeu_si128((__m128i *)(S1 + c), _mm_unpacklo_epi32(s1l, sl));
            _mm_storeu_si128((__m128i *)(S1 + c + 2), _mm_unpackhi_epi32(s1l, sl));
            _mm_storeu_si128((__m128i *)(S1 + c + 4), _mm_unpacklo_epi32(s1h, sh));
            _mm_storeu_si128((__m128i *)(S1 + c + 6), _mm_unpackhi_epi32(s1h, sh));
            _mm_storeu_si128((__m128i *)(S2 + c), _mm_unpacklo_epi32(s2l, zero));
            _mm_storeu_si128((__m128i *)(S2 + c + 2), _mm_unpackhi_epi32(s2l, zero));
            _mm_storeu_si128((__m128i *)(S2 + c + 4), _mm_unpacklo_epi32(s2h, zero));
            _mm_storeu_si128((__m128i *)(S2 + c + 6), _mm_unpackhi_epi32(s2h, zero));
        } else {
            for (int j = 0; j < 8; j++) {
                uint64_t t1 = 0, t2 = 0;
                for (int64_t i = 0; i < k; i++) {
                    uint64_t a = (uint64_t)(int64_t)top[i * plane + c + j];
                    t1 += a;
                    t2 += a * a;
                }
                S1[c + j] = t1;
                S2[c + j] = t2;
            }
        }
    }
    for (; c < w; c++) {  /* the last w % 8 pixels */
        uint64_t t1 = 0, t2 = 0;
        for (int64_t i = 0; i < k; i++) {
            int64_t v = top[i * plane + c];
            t1 += (uint64_t)v;
            t2 += (uint64_t)v * (uint64_t)v;
            big = (v < 0 ? -v : v) > big ? (v < 0 ? -v : v) : big;
            if (wsum != NULL)
                wsum[i * half + c / 2] += (int32_t)v;
        }
        S1[c] = t1;
        S2[c] = t2;
    }
    return big;
}
#endif

/* Rows ya .. yb - 1 of k windows' net counts (frames of h x w bins, window after window; int16 with width 2,
 * int32 with width 4): each pixel's sum (s1) and sum of squares (s2) over the windows, each window's sums over
 * blocks of fy x fx pixels added to blocks (k x (h / fy) x (w / fx); NULL: none), and the largest magnitude,
 * returned: one pass over the counts where numpy takes six. The int16 rows go through row_sums16_sse2 where SSE2
 * is there (with wsum, the pair sums that make the blocks' sums); elsewhere, and for int32 counts, each row's
 * largest magnitude is found first and the sums are 64-bit. 64-bit sums wrap (unsigned: defined); the caller
 * checks that they hold the magnitudes. r1: room for a row of int32 sums. */
static int64_t
net_sums_rows(const void *net, int width, int64_t k, int64_t h, int64_t w, int64_t ya, int64_t yb, int64_t fy,
              int64_t fx, int64_t *s1, int64_t *s2, int64_t *blocks, int32_t *r1, int32_t *wsum)
{
    const int16_t *n16 = (const int16_t *)net;
    const int32_t *n32 = (const int32_t *)net;
    int64_t big = 0, rmax = 0, ow = fx > 0 ? w / fx : 0, oh = fy > 0 ? h / fy : 0;
    for (int64_t row = ya; row < yb; row++) {
        uint64_t *S1 = (uint64_t *)s1 + row * w, *S2 = (uint64_t *)s2 + row * w;
#ifdef HAVE_SSE2
        if (width == 2) {
            int64_t m = row_sums16_sse2(n16, k, h, w, row, S1, S2, wsum);
            big = m > big ? m : big;
            rmax = m > rmax ? m : rmax;
            if (blocks == NULL || (row + 1) % fy)
                continue;
            if (wsum != NULL) {  /* a block row's last row: its blocks from the windows' pair sums */
                for (int64_t i = 0; i < k; i++) {
                    uint64_t *B = (uint64_t *)blocks + (i * oh + row / fy) * ow;
                    int32_t *pairs = wsum + i * (w / 2);
                    for (int64_t b = 0; b < ow; b++) {
                        uint64_t s = 0;
                        for (int64_t j = b * (fx / 2); j < (b + 1) * (fx / 2); j++)
                            s += (uint64_t)(int64_t)pairs[j];
                        B[b] += s;
                    }
                    memset(pairs, 0, (size_t)(w / 2) * sizeof(int32_t));
                }
                rmax = 0;
                continue;
            }
        } else
#endif
        {
            int64_t lo = 0, hi = 0;
            for (int64_t i = 0; i < k; i++) {
                if (width == 2)
                    range16(n16 + (i * h + row) * w, w, &lo, &hi);
                else
                    range32(n32 + (i * h + row) * w, w, &lo, &hi);
            }
            int64_t m = -lo > hi ? -lo : hi;
            big = m > big ? m : big;
            rmax = m > rmax ? m : rmax;
            for (int64_t c = 0; c < w; c++)
                S1[c] = S2[c] = 0;
            for (int64_t i = 0; i < k; i++) {
                int64_t at = (i * h + row) * w;
                for (int64_t c = 0; c < w; c++) {
                    uint64_t a = (uint64_t)(int64_t)(width == 2 ? n16[at + c] : n32[at + c]);
                    S1[c] += a;
                    S2[c] += a * a;
                }
            }
            if (blocks == NULL || (row + 1) % fy)
                continue;
        }
        /* a block row's last row: each window's sums of its fy rows, column by column (in int32 where fy * rmax
           cannot overflow it), then over each block's fx columns */
        for (int64_t i = 0; i < k; i++) {
            int64_t top = (i * h + row + 1 - fy) * w;
            uint64_t *B = (uint64_t *)blocks + (i * oh + row / fy) * ow;
            if (fy * rmax <= INT32_MAX) {
                for (int64_t c = 0; c < w; c++)
                    r1[c] = 0;
                for (int64_t r = 0; r < fy; r++)
                    for (int64_t c = 0; c < w; c++)
                        r1[c] += width == 2 ? n16[top + r * w + c] : n32[top + r * w + c];
                for (int64_t b = 0; b < ow; b++) {
                    uint64_t s = 0;
                    for (int64_t c = b * fx; c < (b + 1) * fx; c++)
                        s += (uint64_t)(int64_t)r1[c];
                    B[b] += s;
                }
            } else {
                for (int64_t r = 0; r < fy; r++)
                    for (int64_t c = 0; c < w; c++)
                        B[c / fx] += (uint64_t)(int64_t)(width == 2 ? n16[top + r * w + c] : n32[top + r * w + c]);
            }
        }
        rmax = 0;
    }
    return big;
}

/* net_sums(net, width, k, h, w, ya, yb, fy, fx, s1, s2, blocks)
 *
 * net: k frames of h x w net counts (int16 with width 2, int32 with width 4), contiguous; s1, s2: int64, h * w;
 * blocks: int64, k * (h / fy) * (w / fx) (fy and fx dividing h and w), or fy = fx = 0 for no block sums. Rows ya ..
 * yb - 1 of s1 and s2 are set and their block rows of blocks added to (ya and yb multiples of fy: another call's
 * rows are other blocks). Returns the largest magnitude among those rows' counts; raises ValueError for an
 * argument this file refuses (the wrapper's checks make that a bug).
 */
static PyObject *
net_sums(PyObject *self, PyObject *args)
{
    Py_buffer nb, s1b, s2b, bb;
    int width;
    long long k, h, w, ya, yb, fy, fx;
    const char *fault = NULL;
    int64_t big = 0;
    int no_memory = 0;

    (void)self;
    if (!PyArg_ParseTuple(args, "y*iLLLLLLLw*w*w*", &nb, &width, &k, &h, &w, &ya, &yb, &fy, &fx, &s1b, &s2b, &bb))
        return NULL;
    if (width != 2 && width != 4)
        fault = "counts are 2 or 4 bytes";
    else if (k < 0 || h <= 0 || w <= 0 || h > (1 << 20) || w > (1 << 20) || k > (nb.len / width) / w / h)
        fault = "frames outside the counts";
    else if (s1b.len / 8 < h * w || s2b.len / 8 < h * w || s1b.buf == s2b.buf || ya < 0 || yb < ya || yb > h)
        fault = "rows outside the sums";
    else if (fy < 0 || fx < 0 || (fy == 0) != (fx == 0))
        fault = "a block size below 0, or one of two";
    else if (fy > 0 && (h % fy || w % fx || ya % fy || yb % fy || bb.len / 8 < k * (h / fy) * (w / fx)))
        fault = "blocks that do not tile the frames, rows that split them, or blocks outside the block sums";
    if (fault == NULL && k > 0 && yb > ya) {
        /* the SSE2 route's pair sums: each window's pixel pairs over a block row (fy * 65536 fits int32) */
        int pairs = fy > 0 && fx % 2 == 0 && fy <= 32767;
        size_t ints = (size_t)w + (pairs ? (size_t)k * (size_t)(w / 2) : 0);
        int32_t *room = PyMem_RawCalloc(ints, sizeof(int32_t));
        no_memory = room == NULL;
        if (room != NULL) {
            Py_BEGIN_ALLOW_THREADS
            big = net_sums_rows(nb.buf, width, k, h, w, ya, yb, fy, fx, (int64_t *)s1b.buf, (int64_t *)s2b.buf,
                                fy > 0 ? (int64_t *)bb.buf : NULL, room, pairs ? room + w : NULL);
            Py_END_ALLOW_THREADS
            PyMem_RawFree(room);
        }
    }
    PyBuffer_Release(&nb);
    PyBuffer_Release(&s1b);
    PyBuffer_Release(&s2b);
    PyBuffer_Release(&bb);
    if (no_memory)
        return PyErr_NoMemory();
    if (fault != NULL) {
        PyErr_SetString(PyExc_ValueError, fault);
        return NULL;
    }
    return PyLong_FromLongLong(big);
}

/* ---- the AEDAT4 reader's batches of LZ4 event packets ---------------------------------------------------- */

typedef size_t (*lz4f_decompress_fn)(void *ctx, void *dst, size_t *dst_size, const void *src, size_t *src_size,
                                     const void *options);
typedef unsigned (*lz4f_is_error_fn)(size_t code);
typedef void (*lz4f_reset_fn)(void *ctx);
/* libzstd's ZSTD_decompressDCtx, ZSTD_findFrameCompressedSize and ZSTD_getFrameContentSize (ZSTD_isError has
 * LZ4F_isError's type) */
typedef size_t (*zstd_decompress_fn)(void *dctx, void *dst, size_t capacity, const void *src, size_t size);
typedef size_t (*zstd_frame_bytes_fn)(const void *src, size_t size);
typedef unsigned long long (*zstd_content_size_fn)(const void *src, size_t size);

/* The codecs of the reader's batches: an AEDAT4 file's LZ4 or Zstandard packets. */
enum { CODEC_LZ4 = 0, CODEC_ZSTD = 1 };

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

/* What every packet of a batch is decoded with: the codec, its library's functions and this thread's context (as
 * addresses), whether checksums are verified, output_limit's terms and the sensor. For LZ4: LZ4F_decompress,
 * LZ4F_isError, LZ4F_resetDecompressionContext and a decompression context; for Zstandard (zdec, zbytes and zsize
 * set, dec and reset not used): ZSTD_decompressDCtx, ZSTD_isError, ZSTD_findFrameCompressedSize,
 * ZSTD_getFrameContentSize and a ZSTD_DCtx. */
typedef struct {
    lz4f_decompress_fn dec;
    lz4f_is_error_fn is_error;
    lz4f_reset_fn reset;
    void *ctx;
    int verify;
    int64_t floor_bytes, ratio, most;
    uint32_t width, height;
    int codec;
    zstd_decompress_fn zdec;
    zstd_frame_bytes_fn zbytes;
    zstd_content_size_fn zsize;
} lz4_job;

/* One Zstandard frame src[0:n] into dst (at most room bytes): evtk.io._compression.decompress's rule for ZSTD (its
 * magic, a stated content size within room and met), and exactly one frame filling the body (anything else goes to
 * the Python route, which decides). The frame's checksum, if it has one, is checked by the library. Returns the
 * bytes written, or -1. */
static int64_t
zstd_frame(const uint8_t *src, int64_t n, uint8_t *dst, int64_t room, const lz4_job *job)
{
    static const uint8_t magic[4] = {0x28, 0xb5, 0x2f, 0xfd};
    const unsigned long long unknown = 0ULL - 1, error = 0ULL - 2;  /* ZSTD_CONTENTSIZE_UNKNOWN, _ERROR */
    if (n < 4 || room < 0 || memcmp(src, magic, 4) != 0)
        return -1;
    size_t whole = job->zbytes(src, (size_t)n);
    if (job->is_error(whole) || whole != (size_t)n)
        return -1;
    unsigned long long stated = job->zsize(src, (size_t)n);
    if (stated == error || (stated != unknown && stated > (unsigned long long)room))
        return -1;
    size_t got = job->zdec(job->ctx, dst, (size_t)room, src, (size_t)n);
    if (job->is_error(got) || got > (size_t)room || (stated != unknown && got != stated))
        return -1;
    return (int64_t)got;
}

/* The n events of a FlatBuffer EVTS vector at ev (16 bytes each: int64 t, uint16 x, uint16 y, a polarity byte,
 * 3 bytes of padding) split into the columns t, x, y and p (a polarity byte not 0 is ON: 1). Returns -1 where an
 * event's x is width or more or its y height or more (the columns then hold the events, checked or not), else 1
 * where a stamp is earlier than the one before it in the vector and 0 where none is: the time-order check that
 * counting windows needs, made while each stamp is in a register (the stamps of packets decoded one after
 * another are compared by the caller, at their edges).
 * With SSE2, eight events at a time: their times moved two by two, their x and y gathered from the events' second
 * halves by shuffles into eight 16-bit lanes each, their polarity bytes packed and compared with 0, and every x
 * and y checked by a saturating subtraction of the largest one allowed (any lane above it leaves a non-zero
 * remainder); the scalar loop takes the rest (a warm 20 M-event read: 15-30 ms less CPU on one thread). */
NOINLINE static int
split_events(const uint8_t *ev, int64_t n, int64_t *t, uint16_t *x, uint16_t *y, uint8_t *p, uint32_t width,
             uint32_t height)
{
    if (width == 0 || height == 0)
        return n > 0 ? -1 : 0;
    int64_t i = 0, first = 0;
    int back = 0;
    if (n > 0)
        memcpy(&first, ev, 8);
#ifdef HAVE_SSE2
    const __m128i zero = _mm_setzero_si128(), one8 = _mm_set1_epi8(1), low8 = _mm_set1_epi32(0xff);
    /* each stamp against the one before it: t - before has its sign bit set exactly where t < before if neither
     * is negative (the difference cannot overflow); the stamps are ORed together to tell. A sign bit set in any
     * difference or any stamp sends the stamps to the exact scalar comparison below: sorted stamps of a
     * recording never go there. */
    __m128i before = _mm_set1_epi64x(first), diffs = zero, stamps = zero;
    const __m128i last_x = _mm_set1_epi16((short)(width > 65536 ? 65535 : width - 1));
    const __m128i last_y = _mm_set1_epi16((short)(height > 65536 ? 65535 : height - 1));
    __m128i over = zero;
    for (; i + 8 <= n; i += 8) {
        const uint8_t *e = ev + 16 * i;
        __m128i e0 = _mm_loadu_si128((const __m128i *)(e + 0)), e1 = _mm_loadu_si128((const __m128i *)(e + 16));
        __m128i e2 = _mm_loadu_si128((const __m128i *)(e + 32)), e3 = _mm_loadu_si128((const __m128i *)(e + 48));
        __m128i e4 = _mm_loadu_si128((const __m128i *)(e + 64)), e5 = _mm_loadu_si128((const __m128i *)(e + 80));
        __m128i e6 = _mm_loadu_si128((const __m128i *)(e + 96)), e7 = _mm_loadu_si128((const __m128i *)(e + 112));
        __m128i t01 = _mm_unpacklo_epi64(e0, e1), t23 = _mm_unpacklo_epi64(e2, e3);
        __m128i t45 = _mm_unpacklo_epi64(e4, e5), t67 = _mm_unpacklo_epi64(e6, e7);
        _mm_storeu_si128((__m128i *)(t + i), t01);
        _mm_storeu_si128((__m128i *)(t + i + 2), t23);
        _mm_storeu_si128((__m128i *)(t + i + 4), t45);
        _mm_storeu_si128((__m128i *)(t + i + 6), t67);
        /* the stamps before them, (t-1, t0), (t1, t2), (t3, t4), (t5, t6): the high lane of one pair, the low of
         * the next */
        __m128i b01 = _mm_castpd_si128(_mm_shuffle_pd(_mm_castsi128_pd(before), _mm_castsi128_pd(t01), 1));
        __m128i b23 = _mm_castpd_si128(_mm_shuffle_pd(_mm_castsi128_pd(t01), _mm_castsi128_pd(t23), 1));
        __m128i b45 = _mm_castpd_si128(_mm_shuffle_pd(_mm_castsi128_pd(t23), _mm_castsi128_pd(t45), 1));
        __m128i b67 = _mm_castpd_si128(_mm_shuffle_pd(_mm_castsi128_pd(t45), _mm_castsi128_pd(t67), 1));
        diffs = _mm_or_si128(diffs, _mm_or_si128(_mm_or_si128(_mm_sub_epi64(t01, b01), _mm_sub_epi64(t23, b23)),
                                                 _mm_or_si128(_mm_sub_epi64(t45, b45), _mm_sub_epi64(t67, b67))));
        stamps = _mm_or_si128(stamps, _mm_or_si128(_mm_or_si128(t01, t23), _mm_or_si128(t45, t67)));
        before = t67;
        /* second halves, as 32-bit lanes [x | y << 16, polarity and padding] two events each: the (x, y) words
         * to the low half, the polarity words to the high */
        __m128i h01 = _mm_shuffle_epi32(_mm_unpackhi_epi64(e0, e1), _MM_SHUFFLE(3, 1, 2, 0));
        __m128i h23 = _mm_shuffle_epi32(_mm_unpackhi_epi64(e2, e3), _MM_SHUFFLE(3, 1, 2, 0));
        __m128i h45 = _mm_shuffle_epi32(_mm_unpackhi_epi64(e4, e5), _MM_SHUFFLE(3, 1, 2, 0));
        __m128i h67 = _mm_shuffle_epi32(_mm_unpackhi_epi64(e6, e7), _MM_SHUFFLE(3, 1, 2, 0));
        __m128i xy03 = _mm_unpacklo_epi64(h01, h23), xy47 = _mm_unpacklo_epi64(h45, h67);  /* 16-bit x, y, x, y .. */
        __m128i pp03 = _mm_unpackhi_epi64(h01, h23), pp47 = _mm_unpackhi_epi64(h45, h67);  /* polarity in byte 0 */
        /* x0 x1 y0 y1 | x2 x3 y2 y3, then x0 x1 x2 x3 | y0 y1 y2 y3 */
        xy03 = _mm_shuffle_epi32(_mm_shufflehi_epi16(_mm_shufflelo_epi16(xy03, _MM_SHUFFLE(3, 1, 2, 0)),
                                                     _MM_SHUFFLE(3, 1, 2, 0)), _MM_SHUFFLE(3, 1, 2, 0));
        xy47 = _mm_shuffle_epi32(_mm_shufflehi_epi16(_mm_shufflelo_epi16(xy47, _MM_SHUFFLE(3, 1, 2, 0)),
                                                     _MM_SHUFFLE(3, 1, 2, 0)), _MM_SHUFFLE(3, 1, 2, 0));
        __m128i xs = _mm_unpacklo_epi64(xy03, xy47), ys = _mm_unpackhi_epi64(xy03, xy47);
        _mm_storeu_si128((__m128i *)(x + i), xs);
        _mm_storeu_si128((__m128i *)(y + i), ys);
        over = _mm_or_si128(over, _mm_or_si128(_mm_subs_epu16(xs, last_x), _mm_subs_epu16(ys, last_y)));
        /* the polarity bytes (0-255 in 32-bit lanes) packed to eight bytes, 1 where not 0 */
        __m128i pb = _mm_packus_epi16(_mm_packs_epi32(_mm_and_si128(pp03, low8), _mm_and_si128(pp47, low8)), zero);
        _mm_storel_epi64((__m128i *)(p + i), _mm_andnot_si128(_mm_cmpeq_epi8(pb, zero), one8));
    }
    if (_mm_movemask_epi8(_mm_cmpeq_epi8(over, zero)) != 0xffff)
        return -1;
    if (_mm_movemask_pd(_mm_castsi128_pd(_mm_or_si128(diffs, stamps))) != 0) {  /* the exact comparison */
        for (int64_t j = 1; j < i; j++)
            back |= t[j] < t[j - 1];
    }
#endif
    uint32_t most_x = 0, most_y = 0;
    int64_t last = i > 0 ? t[i - 1] : first;
    for (; i < n; i++) {
        const uint8_t *e = ev + 16 * i;
        int64_t tt;
        uint16_t xx, yy;
        memcpy(&tt, e, 8);
        memcpy(&xx, e + 8, 2);
        memcpy(&yy, e + 10, 2);
        t[i] = tt;
        x[i] = xx;
        y[i] = yy;
        p[i] = e[12] != 0;
        most_x = xx > most_x ? xx : most_x;
        most_y = yy > most_y ? yy : most_y;
        back |= tt < last;
        last = tt;
    }
    return most_x >= width || most_y >= height ? -1 : back;
}

/* The n_pk packets of one batch in raw[0:n_raw]: packet j's 8-byte header (stream id and body size, int32) at
 * raw[heads[j] - head_base], then its body, which must match sids[j] and sizes[j]; decompressed into stage
 * (at most min(most, floor + ratio * size) bytes), the FlatBuffer's EVTS vector of counts[j] events split into
 * the columns t, x, y, p (n_out events in all) after the previous packet's (x and y within the sensor; a
 * polarity byte not 0 is ON: 1). Returns 1 when every packet decoded and the columns are filled; 0 at anything
 * else (the columns may then hold part of the batch). *back is set to 1 where a packet's stamps go back in time
 * within it (split_events), left as it is otherwise. Called with the GIL released. */
static int
decode_packets(const lz4_job *job, const uint8_t *raw, int64_t n_raw, const int64_t *heads, int64_t head_base,
               const int64_t *sids, const int64_t *sizes, const int64_t *counts, int64_t n_pk, uint8_t *stage,
               int64_t n_stage, int64_t *t, uint16_t *x, uint16_t *y, uint8_t *p, int64_t n_out, int *back)
{
    int64_t cursor = 0;
    for (int64_t j = 0; j < n_pk; j++) {
        if (heads[j] < head_base)
            return 0;
        int64_t h = heads[j] - head_base;
        if (h > n_raw - 8)
            return 0;
        int64_t sid = rd_i32(raw + h), size = rd_i32(raw + h + 4);
        if (sid != sids[j] || size != sizes[j] || size < 0 || size > n_raw - 8 - h)
            return 0;
        /* min(most, floor + ratio * size), without computing a sum or product that could overflow */
        int64_t limit = job->most;
        if (job->ratio == 0 ? job->floor_bytes < job->most
                            : (job->floor_bytes < job->most && size < (job->most - job->floor_bytes) / job->ratio))
            limit = job->floor_bytes + job->ratio * size;
        int64_t room = limit < n_stage ? limit : n_stage;
        int64_t n = job->codec == CODEC_ZSTD
            ? zstd_frame(raw + h + 8, size, stage, room, job)
            : lz4_frame(raw + h + 8, size, stage, room, job->verify, job->dec, job->is_error, job->reset, job->ctx);
        int64_t start, count;
        if (n < 0 || root_vector(stage, n, "EVTS", &start, &count) != 0 || count != counts[j]
            || count > n_out - cursor)
            return 0;
        if (count > 0) {
            int split = split_events(stage + start, count, t + cursor, x + cursor, y + cursor, p + cursor,
                                     job->width, job->height);
            if (split < 0)
                return 0;
            *back |= split;
        }
        cursor += count;
    }
    return cursor == n_out;
}

/* decode_lz4_batch(raw, heads, sids, sizes, counts, verify, decompress, is_error, reset, ctx, stage, floor, ratio,
 *                  most, t, x, y, p, width, height)
 *
 * The event packets of one batch of the AEDAT4 reader, each an LZ4 frame (decode_packets, heads relative to
 * raw). decompress, is_error, reset and ctx: LZ4F_decompress, LZ4F_isError, LZ4F_resetDecompressionContext
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
    lz4_job job = {(lz4f_decompress_fn)(uintptr_t)dec_at, (lz4f_is_error_fn)(uintptr_t)err_at,
                   (lz4f_reset_fn)(uintptr_t)reset_at, (void *)(uintptr_t)ctx_at, verify, floor_bytes, ratio, most,
                   (uint32_t)width, (uint32_t)height, CODEC_LZ4, NULL, NULL, NULL};
    int64_t n_pk = headb.len / 8, n_out = tb.len / 8;

    if (sidb.len / 8 != n_pk || sizeb.len / 8 != n_pk || countb.len / 8 != n_pk || xb.len / 2 != n_out
        || yb.len / 2 != n_out || pb.len != n_out || !job.dec || !job.is_error || !job.reset || !job.ctx
        || width < 0 || height < 0 || floor_bytes < 0 || ratio < 0 || most < 0)
        ok = 0;
    if (ok) {
        int back = 0;  /* (the batch's caller checks the order itself) */
        Py_BEGIN_ALLOW_THREADS
        ok = decode_packets(&job, (const uint8_t *)rawb.buf, rawb.len, (const int64_t *)headb.buf, 0,
                            (const int64_t *)sidb.buf, (const int64_t *)sizeb.buf, (const int64_t *)countb.buf, n_pk,
                            (uint8_t *)stageb.buf, stageb.len, (int64_t *)tb.buf, (uint16_t *)xb.buf,
                            (uint16_t *)yb.buf, (uint8_t *)pb.buf, n_out, &back);
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

/* decode_lz4_range(fd, offs, sids, sizes, counts, starts, k0, k1, batch_events, slack, raw, verify, decompress,
 *                  is_error, reset, ctx, stage, floor, ratio, most, t, x, y, p, width, height[, codec, content_size])
 *
 * codec 0 (the default): LZ4 packets, decompress, is_error, reset and ctx as for decode_lz4_batch; codec 1:
 * Zstandard packets, decompress, is_error and reset the addresses of libzstd's ZSTD_decompressDCtx, ZSTD_isError
 * and ZSTD_findFrameCompressedSize, ctx a ZSTD_DCtx of this thread and content_size ZSTD_getFrameContentSize's.
 *
 * Rows k0 .. k1 - 1 of the AEDAT4 reader's packets (row k: its body at file offset offs[k], after its 8-byte
 * header; sids, sizes and counts as for decode_lz4_batch; its events go to columns[starts[k]:starts[k + 1]]),
 * batch after batch as the reader cuts them (from row k up to the row before the first whose start passes
 * starts[k] + batch_events, at least one row, at most k1), each batch's bytes read from the file descriptor
 * fd into raw with pread, then decode_packets: the reader's whole loop over its batches, the GIL released
 * from the first batch to the last instead of taken back after each.
 *
 * Returns (k, need_raw, need_stage, batches, back): k1 when every batch decoded; else the first row of the batch
 * left, with need_raw or need_stage the bytes raw or stage lack for it (the caller grows the buffer and calls
 * again), or both 0 where the caller's Python loop is to decode that batch (packets far apart in the file, a
 * short read, anything decode_packets declines); batches: how many decoded, or -1 on a platform without pread
 * (nothing done); back: 1 where the stamps of a packet of the batches decoded go back in time within it, else 0
 * (the packets' edges are the caller's to compare).
 */
static PyObject *
decode_lz4_range(PyObject *self, PyObject *args)
{
    Py_buffer offb, sidb, sizeb, countb, startb, rawb, stageb, tb, xb, yb, pb;
    int fd, verify;
    Py_ssize_t k0, k1;
    long long batch_events, slack;
    unsigned long long dec_at, err_at, reset_at, ctx_at, size_at = 0;
    long long floor_bytes, ratio, most;
    int width, height, codec = CODEC_LZ4;

    (void)self;
    if (!PyArg_ParseTuple(args, "iy*y*y*y*y*nnLLw*pKKKKw*LLLw*w*w*w*ii|iK", &fd, &offb, &sidb, &sizeb, &countb,
                          &startb, &k0, &k1, &batch_events, &slack, &rawb, &verify, &dec_at, &err_at, &reset_at,
                          &ctx_at, &stageb, &floor_bytes, &ratio, &most, &tb, &xb, &yb, &pb, &width, &height, &codec,
                          &size_at))
        return NULL;
    int zstd = codec == CODEC_ZSTD;
    lz4_job job = {zstd ? NULL : (lz4f_decompress_fn)(uintptr_t)dec_at, (lz4f_is_error_fn)(uintptr_t)err_at,
                   zstd ? NULL : (lz4f_reset_fn)(uintptr_t)reset_at, (void *)(uintptr_t)ctx_at, verify, floor_bytes,
                   ratio, most, (uint32_t)width, (uint32_t)height, codec,
                   zstd ? (zstd_decompress_fn)(uintptr_t)dec_at : NULL,
                   zstd ? (zstd_frame_bytes_fn)(uintptr_t)reset_at : NULL,
                   zstd ? (zstd_content_size_fn)(uintptr_t)size_at : NULL};
    const int64_t *offs = (const int64_t *)offb.buf, *sids = (const int64_t *)sidb.buf;
    const int64_t *sizes = (const int64_t *)sizeb.buf, *counts = (const int64_t *)countb.buf;
    const int64_t *starts = (const int64_t *)startb.buf;
    uint8_t *raw = (uint8_t *)rawb.buf, *stage = (uint8_t *)stageb.buf;
    int64_t *t = (int64_t *)tb.buf;
    uint16_t *x = (uint16_t *)xb.buf, *y = (uint16_t *)yb.buf;
    uint8_t *p = (uint8_t *)pb.buf;
    int64_t n_rows = offb.len / 8, n_out = tb.len / 8, n_raw = rawb.len, n_stage = stageb.len;
    const char *fault = NULL;
    int64_t k = k0, need_raw = 0, need_stage = 0, batches = 0;
    int back = 0;

    if (sidb.len / 8 != n_rows || sizeb.len / 8 != n_rows || countb.len / 8 != n_rows
        || startb.len / 8 != n_rows + 1)
        fault = "offs, sids, sizes and counts need one entry a row, starts one more";
    else if (xb.len / 2 != n_out || yb.len / 2 != n_out || pb.len != n_out)
        fault = "the columns differ in length";
    else if (k0 < 0 || k0 > k1 || k1 > n_rows)
        fault = "rows k0 .. k1 outside the rows";
    else if (batch_events < 1 || batch_events > ((int64_t)1 << 40) || slack < 0 || slack > ((int64_t)1 << 40))
        fault = "batch_events or slack out of range";
    else if (codec != CODEC_LZ4 && codec != CODEC_ZSTD)
        fault = "the codec is 0 (LZ4) or 1 (Zstandard)";
    else if ((zstd ? (!job.zdec || !job.zbytes || !job.zsize) : (!job.dec || !job.reset)) || !job.is_error || !job.ctx
             || width < 0 || height < 0 || floor_bytes < 0 || ratio < 0 || most < 0)
        fault = "a codec address is 0, or a size is negative";
    if (fault == NULL) {
#ifdef _WIN32
        (void)fd;  /* no pread here: batches -1 tells the caller to take every batch the Python way */
        batches = -1;
#else
        Py_BEGIN_ALLOW_THREADS
        while (k < k1) {
            /* the batch: rows k .. kb - 1, kb the row before the first whose start passes starts[k] + batch_events
             * (numpy's searchsorted(starts, ..., "right") over k + 1 .. k1), at least k + 1, at most k1 */
            if (starts[k] < 0 || starts[k] > n_out)
                break;
            int64_t v = starts[k] + batch_events, lo = k + 1, hi = k1 + 1;
            while (lo < hi) {
                int64_t mid = lo + (hi - lo) / 2;
                if (starts[mid] > v)
                    hi = mid;
                else
                    lo = mid + 1;
            }
            int64_t kb = lo - 1 < k + 1 ? k + 1 : (lo - 1 > k1 ? k1 : lo - 1);
            int64_t first = starts[k], last = starts[kb];
            if (last < first || last > n_out)
                break;
            /* the batch's bytes: from row k's header to row kb - 1's end, unless other packets lie between */
            int64_t body = 0, bad = 0;
            for (int64_t j = k; j < kb; j++) {
                if (offs[j] < 8 || sizes[j] < 0 || sizes[j] > INT32_MAX || offs[j] > ((int64_t)1 << 60))
                    bad = 1;
                else
                    body += sizes[j] + 8;
            }
            if (bad)
                break;
            int64_t o0 = offs[k] - 8;
            int64_t span = offs[kb - 1] + sizes[kb - 1] - o0;
            if (span < 8 || span > 2 * body + slack)
                break;
            if (span > n_raw) {
                need_raw = span;
                break;
            }
            if (16 * (last - first) + 3 * slack > n_stage) {
                need_stage = 16 * (last - first) + 3 * slack;
                break;
            }
            int64_t got = 0;
            while (got < span) {
                ssize_t r = pread(fd, raw + got, (size_t)(span - got), (off_t)(o0 + got));
                if (r < 0 && errno == EINTR)
                    continue;
                if (r <= 0)
                    break;
                got += r;
            }
            if (got < span)
                break;
            int batch_back = 0;  /* (kept only where the whole batch decoded) */
            if (!decode_packets(&job, raw, span, offs + k, o0 + 8, sids + k, sizes + k, counts + k, kb - k, stage,
                                n_stage, t + first, x + first, y + first, p + first, last - first, &batch_back))
                break;
            back |= batch_back;
            batches++;
            k = kb;
        }
        Py_END_ALLOW_THREADS
#endif
    }
    PyBuffer_Release(&offb);
    PyBuffer_Release(&sidb);
    PyBuffer_Release(&sizeb);
    PyBuffer_Release(&countb);
    PyBuffer_Release(&startb);
    PyBuffer_Release(&rawb);
    PyBuffer_Release(&stageb);
    PyBuffer_Release(&tb);
    PyBuffer_Release(&xb);
    PyBuffer_Release(&yb);
    PyBuffer_Release(&pb);
    if (fault != NULL) {
        PyErr_SetString(PyExc_ValueError, fault);
        return NULL;
    }
    return Py_BuildValue("(nLLLi)", (Py_ssize_t)k, (long long)need_raw, (long long)need_stage, (long long)batches,
                         back);
}

/* ---- the Prophesee decoders' states ----------------------------------------------------------------------- */

/* Whether state[k] lies in [lo[k], hi[k]) for each of its n values: the states a decoder's words can leave (the
 * wrappers in evtk/_native.py send other states to numpy). A raw call with another is refused, so that no sum,
 * step or count of the decoding can overflow whatever the caller passes. */
static int
state_in(const int64_t *state, const int64_t *lo, const int64_t *hi, int n)
{
    for (int k = 0; k < n; k++)
        if (state[k] < lo[k] || state[k] >= hi[k])
            return 0;
    return 1;
}

#define STATE_MOST ((int64_t)1 << 40) /* the epochs and vector bases a state may hold (each word adds 12 at most) */
#define SENSOR_MOST ((int64_t)1 << 16) /* the widest and tallest sensor (the coordinates are uint16) */

/* ---- Prophesee EVT 3.0 words ------------------------------------------------------------------------------ */

/* Outcomes of evt3_run (the wrapper maps them to the Prophesee decoders' status codes). */
enum { E3_OK = 0, E3_TYPE = 1, E3_COORD = 2, E3_FULL = 3 };

/* Set bits of each 12-bit value (filled as the module loads), and the index of the lowest set bit of v (v not 0),
 * without compiler built-ins. */
static uint8_t pop12[4096];

static void
fill_pop12(void)
{
    for (unsigned v = 1; v < 4096; v++)
        pop12[v] = (uint8_t)(pop12[v >> 1] + (v & 1u));
}

static inline int
popcount12(unsigned v)
{
    return pop12[v & 0xFFFu];
}

static inline int
lowest_bit(unsigned v)
{
    int k = 0;
    for (; !(v & 1u); v >>= 1)
        k++;
    return k;
}

/* The decoder between words: what every word needs from the words before it, the outputs' fill, and the time
 * range of the events written. */
typedef struct {
    int64_t high, low, epoch, y, base, pol, now;
    int64_t n, m, t_min, t_max;
} e3_state;

typedef struct {
    int64_t *t, *tt;
    uint16_t *x, *y;
    uint8_t *p, *tk, *tch;
    int64_t cap, cap_tr, width, height;
    int decode;
} e3_out;

/* The time of an event at the state's time words: epoch << 24 | high << 12 | low, in unsigned arithmetic (any
 * state wraps, defined, instead of overflowing). */
static inline int64_t
e3_now(const e3_state *s)
{
    return (int64_t)(((uint64_t)s->epoch << 24) | ((uint64_t)s->high << 12) | (uint64_t)s->low);
}

static inline void
e3_seen(e3_state *s)
{
    s->t_min = s->now < s->t_min ? s->now : s->t_min;
    s->t_max = s->now > s->t_max ? s->now : s->t_max;
}

/* One word taken exactly as the format describes it (see evt3_run): its effects on the state and outputs, or an
 * outcome other than E3_OK when the decoding stops at it (its effects not taken, but for the events of a vector
 * word before one off the sensor). */
static int
e3_word(unsigned w, e3_state *s, const e3_out *o)
{
    unsigned kind = w >> 12, v = w & 0xFFF;
    switch (kind) {
    case 0:
        s->y = v & 0x7FF;
        return E3_OK;
    case 2: {
        int64_t xx = v & 0x7FF;
        if (o->decode && s->n >= o->cap)
            return E3_FULL;
        if (xx >= o->width || s->y >= o->height)
            return E3_COORD;
        if (o->decode) {
            o->t[s->n] = s->now;
            o->x[s->n] = (uint16_t)xx;
            o->y[s->n] = (uint16_t)s->y;
            o->p[s->n] = (uint8_t)((v >> 11) & 1);
        }
        s->n++;
        e3_seen(s);
        return E3_OK;
    }
    case 4:
    case 5: {
        unsigned mask = kind == 4 ? v : (v & 0xFF);
        int64_t n0 = s->n;
        int outcome = E3_OK;
        if (o->decode && s->n + popcount12(mask) > o->cap)
            return E3_FULL;
        for (; mask; mask &= mask - 1) {
            int64_t xx = s->base + lowest_bit(mask);
            if (xx < 0 || xx >= o->width || s->y >= o->height) {
                outcome = E3_COORD;
                break;
            }
            if (o->decode) {
                o->t[s->n] = s->now;
                o->x[s->n] = (uint16_t)xx;
                o->y[s->n] = (uint16_t)s->y;
                o->p[s->n] = (uint8_t)s->pol;
            }
            s->n++;
        }
        if (s->n > n0)
            e3_seen(s);
        if (outcome == E3_OK)
            s->base += kind == 4 ? 12 : 8;
        return outcome;
    }
    case 3:
        s->base = v & 0x7FF;
        s->pol = (v >> 11) & 1;
        return E3_OK;
    case 6:
        s->low = v;
        s->now = e3_now(s);
        return E3_OK;
    case 8:
        if ((int64_t)v < s->high && s->high - (int64_t)v > 2048)
            s->epoch++;
        s->high = v;
        s->now = e3_now(s);
        return E3_OK;
    case 10:
        if (o->decode) {
            if (s->m >= o->cap_tr)
                return E3_FULL;
            o->tt[s->m] = s->now;
            o->tk[s->m] = (v & 1) ? 1 : 2;
            o->tch[s->m] = (uint8_t)((v >> 8) & 0xF);
        }
        s->m++;
        return E3_OK;
    case 7:
    case 14:
    case 15:
        return E3_OK;
    default:
        return E3_TYPE;
    }
}

/* The word types e3_fast leaves to e3_word (bit k: type k): triggers and the types that are none. */
#define E3_SLOW_TYPES ((1u << 1) | (1u << 9) | (1u << 10) | (1u << 11) | (1u << 12) | (1u << 13))
/* Most words e3_fast takes at a time (its events, at most 12 a word, stay in the cache for the check after). */
#define E3_CHUNK_WORDS 4096

/* Words [i, end) decoded fast, from state s, where their events cannot outgrow the columns (the caller made sure
 * that 12 a word fit). An EVT_ADDR_X word's event is written whatever the word (only an event word moves the fill
 * on past it), so that the fill takes no branch on the y, x and time words, which come in no order a predictor
 * learns.
 * Stops at the first word it leaves to e3_word (a trigger, a word of no type, a vector word whose events could
 * pass the sensor's width); an event off the sensor it writes all the same (the caller checks the coordinates
 * written, and takes the words again with e3_word where one is off). Returns the index of the first word not
 * taken. Compiled on its own (NOINLINE): inlined, it lost the registers to its caller's copy of the state. */
NOINLINE static int64_t
e3_fast(const uint16_t *words, int64_t i, int64_t end, e3_state *s, const e3_out *o)
{
    /* in locals (the columns' uint8 stores may alias anything in memory) only what every word needs: the time as
     * the one value now = epoch << 24 | high << 12 | low (unsigned arithmetic: any state wraps, defined), y and
     * the fill; the vector base and polarity, which only vector and EVT_VECT_BASE_X words touch, stay in *s, so
     * that the loop's values fit in the registers */
    uint64_t now = ((uint64_t)s->epoch << 24) | ((uint64_t)s->high << 12) | (uint64_t)s->low;
    int64_t yy = s->y, n = s->n;
    int64_t *const t = o->t;
    uint16_t *const x = o->x, *const y = o->y;
    uint8_t *const p = o->p;
    const uint16_t *at = words + i, *const stop = words + end;
    for (; at < stop; at++) {
        unsigned w = *at, kind = w >> 12, v = w & 0xFFF;
        if ((E3_SLOW_TYPES >> kind) & 1u)
            break;
        t[n] = (int64_t)now;
        x[n] = (uint16_t)(v & 0x7FF);
        y[n] = (uint16_t)yy;
        p[n] = (uint8_t)(v >> 11);
        n += kind == 2;
        if ((kind | 1u) == 5u) { /* a vector word (4: 12 bits, 5: 8): its events, then the base moves on */
            unsigned events = kind == 4 ? v : (v & 0xFFu);
            int64_t base = s->base;
            if (events && (base < 0 || base > o->width - 12))
                break;
            for (; events; events &= events - 1, n++) {
                t[n] = (int64_t)now;
                x[n] = (uint16_t)(base + lowest_bit(events));
                y[n] = (uint16_t)yy;
                p[n] = (uint8_t)s->pol;
            }
            s->base = base + (kind == 4 ? 12 : 8);
            continue;
        }
        yy = kind == 0 ? (int64_t)(v & 0x7FF) : yy;
        now = kind == 6 ? (now & ~(uint64_t)0xFFF) | v : now;
        if (kind == 3) {
            s->base = (int64_t)(v & 0x7FF);
            s->pol = (int64_t)(v >> 11);
        } else if (kind == 8) {
            uint64_t high = (now >> 12) & 0xFFF, wrap = v < high && high - v > 2048;
            now = (((now >> 24) + wrap) << 24) | ((uint64_t)v << 12) | (now & 0xFFF);
        }
    }
    s->high = (int64_t)((now >> 12) & 0xFFF), s->epoch = (int64_t)(now >> 24), s->low = (int64_t)(now & 0xFFF);
    s->y = yy, s->now = (int64_t)now, s->n = n;
    return (int64_t)(at - words);
}

/* Words [0, n_words) from state s (its values in range: high and low below 4096, y below 2048, epoch and base not
 * negative and below 2**40, pol 0 or 1; evt3_run checks); returns the outcome and sets *bad to the word stopped at.
 *
 * Decoding, most words go through e3_fast a chunk at a time; the chunk's events are then checked against the
 * sensor, and where one is off the chunk is taken again from its start with e3_word, which stops at it. The words
 * e3_fast leaves, those where the columns are within 12 events of full, and every word when counting, go
 * through e3_word. Either way the words are taken one after another, so the results are e3_word's alone. */
static int
e3_decode(const uint16_t *words, int64_t n_words, e3_state *s, const e3_out *o, int64_t *bad)
{
    int64_t i = 0;
    int outcome = E3_OK;
    while (i < n_words && outcome == E3_OK) {
        int64_t fits = o->decode ? (o->cap - s->n) / 12 : 0;
        if (fits > 0) {
            int64_t end = n_words - i < fits ? n_words : i + fits;
            end = end - i > E3_CHUNK_WORDS ? i + E3_CHUNK_WORDS : end;
            e3_state start = *s;
            int64_t first = i;
            i = e3_fast(words, i, end, s, o);
            uint16_t most_x = 0, most_y = 0;
            int64_t t_min = s->t_min, t_max = s->t_max;
            for (int64_t k = start.n; k < s->n; k++) {
                most_x = o->x[k] > most_x ? o->x[k] : most_x;
                most_y = o->y[k] > most_y ? o->y[k] : most_y;
                t_min = o->t[k] < t_min ? o->t[k] : t_min;
                t_max = o->t[k] > t_max ? o->t[k] : t_max;
            }
            if (s->n > start.n && (most_x >= o->width || most_y >= o->height)) {
                int64_t taken = i; /* an event off the sensor: the chunk again, exactly */
                *s = start;
                for (i = first; i < taken; i++)
                    if ((outcome = e3_word(words[i], s, o)) != E3_OK)
                        break;
                continue;
            }
            s->t_min = t_min, s->t_max = t_max; /* the time range of the events e3_fast wrote (it keeps none) */
            if (i == end)
                continue;
        }
        outcome = e3_word(words[i], s, o); /* a word e3_fast leaves, or one near full columns, or counting */
        if (outcome == E3_OK)
            i++;
    }
    *bad = outcome == E3_OK ? -1 : i;
    return outcome;
}

/* The end of a decoder's call: its buffers released, then ValueError(fault) where fault is set, else the decoders'
 * (events, triggers, outcome, index of the word stopped at or -1, min t, max t). */
static PyObject *
decoded(Py_buffer *const *bufs, int n_bufs, const char *fault, int64_t n, int64_t m, int outcome, int64_t bad,
        int64_t t_min, int64_t t_max)
{
    for (int k = 0; k < n_bufs; k++)
        PyBuffer_Release(bufs[k]);
    if (fault != NULL) {
        PyErr_SetString(PyExc_ValueError, fault);
        return NULL;
    }
    return Py_BuildValue("LLiLLL", (long long)n, (long long)m, outcome, (long long)bad, (long long)t_min,
                         (long long)t_max);
}

/* evt3_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch)
 *
 * EVT 3.0 words (uint16, the type in the top four bits) decoded one after another from state (six int64, updated
 * in place to the state after the words whose effects stand: time high, time low, epoch, y, vector base x,
 * polarity), to the results of evtk.io.prophesee._evt3's numpy decoder:
 *   0 EVT_ADDR_Y sets y; 2 EVT_ADDR_X is one event at x (bits 0..10), polarity bit 11; 3 VECT_BASE_X sets the
 *   base x and polarity; 4 VECT_12 and 5 VECT_8 are events at base + k for each set bit k of their 12 or 8 low
 *   bits, and move the base on by 12 or 8; 6 EVT_TIME_LOW and 8 EVT_TIME_HIGH set bits 0..11 and 12..23 of
 *   the time (a time high more than 2048 below the one before is a wrap: the epoch counts them); 10 EXT_TRIGGER
 *   is a trigger (kind 1 rising at bit 0 set, else 2 falling; channel bits 8..11); 7, 14 and 15 carry nothing.
 * The time of an event or trigger is epoch << 24 | high << 12 | low.
 *
 * Stops at a word of another type (E3_TYPE, its effects not taken), at the first event off the width x height
 * sensor (E3_COORD: the events of its word before it are kept, the word's other effects are not) or, with
 * decode, at the first event word whose events no longer all fit t, or trigger that no longer fits tt (E3_FULL,
 * the word not taken). Without decode nothing is written (the columns may be empty).
 *
 * Returns (events, triggers, outcome, index of the word stopped at or -1, min t, max t of the events; 2**62 and
 * -2**62 without events). The GIL is released throughout.
 */
static PyObject *
evt3_run(PyObject *self, PyObject *args)
{
    Py_buffer wb, sb, tb, xb, yb, pb, ttb, tkb, tchb;
    long long width, height;
    int decode, outcome = E3_OK;
    int64_t bad = -1;
    e3_state s;
    const char *fault = NULL;

    (void)self;
    if (!PyArg_ParseTuple(args, "y*w*LLpw*w*w*w*w*w*w*", &wb, &sb, &width, &height, &decode, &tb, &xb, &yb, &pb,
                          &ttb, &tkb, &tchb))
        return NULL;
    int64_t *state = (int64_t *)sb.buf;
    e3_out o = {(int64_t *)tb.buf, (int64_t *)ttb.buf, (uint16_t *)xb.buf, (uint16_t *)yb.buf, (uint8_t *)pb.buf,
                (uint8_t *)tkb.buf, (uint8_t *)tchb.buf, tb.len / 8, ttb.len / 8, width, height, decode};

    /* time high, time low, epoch, y, vector base x, polarity */
    static const int64_t lo3[6] = {0, 0, 0, 0, 0, 0}, hi3[6] = {4096, 4096, STATE_MOST, 2048, STATE_MOST, 2};
    if (sb.len != 6 * 8)
        fault = "the state is six int64";
    else if (!state_in(state, lo3, hi3, 6))
        fault = "a state EVT 3.0 words cannot leave";
    else if (width < 0 || width > SENSOR_MOST || height < 0 || height > SENSOR_MOST)
        fault = "the sensor's width and height are 0 to 65536";
    else if (xb.len / 2 != o.cap || yb.len / 2 != o.cap || pb.len != o.cap || tkb.len != o.cap_tr
             || tchb.len != o.cap_tr)
        fault = "the columns differ in length";
    if (fault == NULL) {
        Py_BEGIN_ALLOW_THREADS
        s.high = state[0], s.low = state[1], s.epoch = state[2], s.y = state[3], s.base = state[4];
        s.pol = state[5];
        s.now = e3_now(&s);
        s.n = s.m = 0;
        s.t_min = (int64_t)1 << 62, s.t_max = -((int64_t)1 << 62);
        outcome = e3_decode((const uint16_t *)wb.buf, wb.len / 2, &s, &o, &bad);
        state[0] = s.high, state[1] = s.low, state[2] = s.epoch, state[3] = s.y, state[4] = s.base;
        state[5] = s.pol;
        Py_END_ALLOW_THREADS
    }
    Py_buffer *const bufs[] = {&wb, &sb, &tb, &xb, &yb, &pb, &ttb, &tkb, &tchb};
    return decoded(bufs, 9, fault, s.n, s.m, outcome, bad, s.t_min, s.t_max);
}

/* evt3_scan(words)
 *
 * The counts and the effect on the decoder's state of EVT 3.0 words, up to the first word of no type, without
 * decoding them (evtk.io.prophesee._evt3.scan): (events, triggers, index of the word of no type or -1, and the
 * effect: the last y, the last time low, the first and the last time high (each -1 where no word sets it), the
 * wraps between the time highs, the last vector base word's 12 low bits (x and polarity; -1 if none) and the
 * vector steps after it (after the start if none)). Events off any sensor are counted.
 *
 * The loop branches only at time-high words and at a word of no type: each word's events are counted through
 * tables, and its index and the vector steps so far are stored under its type, so that the last word of each
 * type is known at the end (a third of the time of keeping each value by selection). The GIL is released.
 */
static PyObject *
evt3_scan(PyObject *self, PyObject *args)
{
    Py_buffer wb;
    /* the bits of a vector word that are events, and the steps it moves the base on, by type */
    static const unsigned events_mask[16] = {0, 0, 0, 0, 0xFFF, 0xFF, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
    static const int64_t step[16] = {0, 0, 0, 0, 12, 8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
    /* bit k: type k is none of EVT 3.0's (1, 9, 11, 12, 13) */
    const unsigned none = (1u << 1) | (1u << 9) | (1u << 11) | (1u << 12) | (1u << 13);

    (void)self;
    if (!PyArg_ParseTuple(args, "y*", &wb))
        return NULL;
    const uint16_t *words = (const uint16_t *)wb.buf;
    int64_t n_words = wb.len / 2, n_ev = 0, n_tr = 0, stop = -1;
    int64_t first_high = -1, last_high = -1, wraps = 0, steps = 0;
    int64_t last[16], steps_at[16];
    Py_BEGIN_ALLOW_THREADS
    for (int k = 0; k < 16; k++)
        last[k] = -1, steps_at[k] = 0;
    for (int64_t i = 0; i < n_words; i++) {
        unsigned w = words[i], kind = w >> 12, v = w & 0xFFF;
        if ((none >> kind) & 1u) {
            stop = i;
            break;
        }
        n_ev += (kind == 2) + popcount12(v & events_mask[kind]);
        n_tr += kind == 10;
        steps += step[kind];
        last[kind] = i;
        steps_at[kind] = steps;
        if (kind == 8) {
            if (first_high < 0)
                first_high = v;
            else if ((int64_t)v < last_high && last_high - (int64_t)v > 2048)
                wraps++;
            last_high = v;
        }
    }
    Py_END_ALLOW_THREADS
    int64_t yy = last[0] >= 0 ? (int64_t)(words[last[0]] & 0x7FF) : -1;
    int64_t low = last[6] >= 0 ? (int64_t)(words[last[6]] & 0xFFF) : -1;
    int64_t base = last[3] >= 0 ? (int64_t)(words[last[3]] & 0xFFF) : -1;
    steps -= last[3] >= 0 ? steps_at[3] : 0;
    PyBuffer_Release(&wb);
    return Py_BuildValue("LLL(LLLLLLL)", (long long)n_ev, (long long)n_tr, (long long)stop, (long long)yy,
                         (long long)low, (long long)first_high, (long long)last_high, (long long)wraps,
                         (long long)base, (long long)steps);
}

/* ---- Prophesee EVT 2.0 words and DAT events --------------------------------------------------------------- */

/* EVT 2.0 words [0, n_words) from the time high *high and its wraps *epoch (updated), the events and triggers
 * after the first *n and *m of o's columns (EVT 3.0's output struct; updated, as the events' time range *t_min,
 * *t_max): evt2_run's loop, compiled on its own (NOINLINE: inlined, it shared the registers with evt2_run's
 * buffers). Returns the outcome and sets *at to the word it stopped at (n_words when none). */
NOINLINE static int
e2_decode(const uint32_t *words, int64_t n_words, int64_t *high_io, int64_t *epoch_io, const e3_out *o, int64_t *n_io,
          int64_t *m_io, int64_t *t_min_io, int64_t *t_max_io, int64_t *at)
{
    int64_t high = *high_io, epoch = *epoch_io, n = *n_io, m = *m_io, t_min = *t_min_io, t_max = *t_max_io;
    const int64_t width = o->width, height = o->height, cap = o->cap;
    const int decode = o->decode;
    int64_t *const t = o->t;
    uint16_t *const x = o->x, *const y = o->y;
    uint8_t *const p = o->p;
    int outcome = E3_OK;
    int64_t base = (int64_t)(((uint64_t)epoch << 34) | ((uint64_t)high << 6));
    int64_t i = 0;
    for (; i < n_words; i++) {
        uint32_t w = words[i];
        unsigned kind = w >> 28;
        if (kind <= 1) {
            int64_t xx = (w >> 11) & 0x7FF, yy = w & 0x7FF;
            if (xx >= width || yy >= height) { outcome = E3_COORD; break; }
            int64_t now = base | ((w >> 22) & 0x3F);
            if (decode) {
                if (n >= cap) { outcome = E3_FULL; break; }
                t[n] = now;
                x[n] = (uint16_t)xx;
                y[n] = (uint16_t)yy;
                p[n] = (uint8_t)kind;
            }
            t_min = now < t_min ? now : t_min;
            t_max = now > t_max ? now : t_max;
            n++;
        } else if (kind == 8) {
            int64_t v = w & 0xFFFFFFF;
            if (v < high && high - v > ((int64_t)1 << 27))
                epoch++;
            high = v;
            base = (int64_t)(((uint64_t)epoch << 34) | ((uint64_t)high << 6));
        } else if (kind == 10) {
            if (decode) {
                if (m >= o->cap_tr) { outcome = E3_FULL; break; }
                o->tt[m] = base | ((w >> 22) & 0x3F);
                o->tk[m] = (w & 1) ? 1 : 2;
                o->tch[m] = (uint8_t)((w >> 8) & 0x1F);
            }
            m++;
        } else if (kind != 14 && kind != 15) {
            outcome = E3_TYPE;
            break;
        }
    }
    *high_io = high, *epoch_io = epoch, *n_io = n, *m_io = m, *t_min_io = t_min, *t_max_io = t_max, *at = i;
    return outcome;
}

/* evt2_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch)
 *
 * EVT 2.0 words (uint32, the type in the top four bits) taken one after another from state (two int64, updated in
 * place: the last time high, the epoch), to the results of evtk.io.prophesee.decoders' numpy decoder: CD_OFF and
 * CD_ON (0, 1) are an event at x (bits 11..21), y (bits 0..10), polarity the type, time base | bits 22..27;
 * EV_TIME_HIGH (8) sets the time high (bits 0..27; a drop of more than 2**27 is a wrap: the epoch counts them),
 * the time base being epoch << 34 | high << 6; EXT_TRIGGER (10) is a trigger at base | bits 22..27 (kind 1 rising
 * at bit 0 set, else 2; channel bits 8..12); OTHERS and CONTINUED (14, 15) carry nothing.
 *
 * Stops at an event off the width x height sensor (E3_COORD) or a word of another type (E3_TYPE), the word's
 * effects not taken, or, decoding, where the columns are full (E3_FULL; evtk._native's wrapper gives columns as
 * long as the words). Returns (events, triggers, outcome, index of the word stopped at or -1, min t, max t of the
 * events; 2**62 and -2**62 without any). The GIL is released throughout.
 */
static PyObject *
evt2_run(PyObject *self, PyObject *args)
{
    Py_buffer wb, sb, tb, xb, yb, pb, ttb, tkb, tchb;
    long long width, height;
    int decode, outcome = E3_OK;
    int64_t n = 0, m = 0, bad = -1, t_min = (int64_t)1 << 62, t_max = -((int64_t)1 << 62);
    const char *fault = NULL;

    (void)self;
    if (!PyArg_ParseTuple(args, "y*w*LLpw*w*w*w*w*w*w*", &wb, &sb, &width, &height, &decode, &tb, &xb, &yb, &pb,
                          &ttb, &tkb, &tchb))
        return NULL;
    const uint32_t *words = (const uint32_t *)wb.buf;
    int64_t *state = (int64_t *)sb.buf, *t = (int64_t *)tb.buf, *tt = (int64_t *)ttb.buf;
    uint16_t *x = (uint16_t *)xb.buf, *y = (uint16_t *)yb.buf;
    uint8_t *p = (uint8_t *)pb.buf, *tk = (uint8_t *)tkb.buf, *tch = (uint8_t *)tchb.buf;
    int64_t n_words = wb.len / 4, cap = tb.len / 8, cap_tr = ttb.len / 8;

    static const int64_t lo2[2] = {0, 0}, hi2[2] = {(int64_t)1 << 28, STATE_MOST}; /* time high, epoch */
    if (sb.len != 2 * 8)
        fault = "the state is two int64";
    else if (!state_in(state, lo2, hi2, 2))
        fault = "a state EVT 2.0 words cannot leave";
    else if (width < 0 || width > SENSOR_MOST || height < 0 || height > SENSOR_MOST)
        fault = "the sensor's width and height are 0 to 65536";
    else if (xb.len / 2 != cap || yb.len / 2 != cap || pb.len != cap || tkb.len != cap_tr || tchb.len != cap_tr)
        fault = "the columns differ in length";
    if (fault == NULL) {
        Py_BEGIN_ALLOW_THREADS
        e3_out o = {t, tt, x, y, p, tk, tch, cap, cap_tr, (int64_t)width, (int64_t)height, decode};
        int64_t high = state[0], epoch = state[1], i = 0;
        outcome = e2_decode(words, n_words, &high, &epoch, &o, &n, &m, &t_min, &t_max, &i);
        bad = outcome == E3_OK ? -1 : i;
        state[0] = high, state[1] = epoch;
        Py_END_ALLOW_THREADS
    }
    Py_buffer *const bufs[] = {&wb, &sb, &tb, &xb, &yb, &pb, &ttb, &tkb, &tchb};
    return decoded(bufs, 9, fault, n, m, outcome, bad, t_min, t_max);
}

/* dat_run(words, state, width, height, decode, t, x, y, p)
 *
 * DAT CD events (pairs of uint32: time stamp, data; a last odd word is left) taken one after another from state
 * (two int64, updated in place: the last raw time stamp, -1 before the first, and the epoch), to the results of
 * evtk.io.prophesee.decoders' numpy decoder: x is bits 0..13 of the data, y bits 14..27, the polarity ON where
 * any of bits 28..31 is set; a time stamp more than 2**31 below the one before is a wrap of the counter (the epoch
 * counts them), the time epoch << 32 | stamp.
 *
 * Stops at an event off the width x height sensor (E3_COORD; its stamp still moves the clock, as numpy's decoder
 * reads it) or, decoding, where the columns are full (E3_FULL). Returns (events, 0, outcome, index of the event
 * stopped at or -1, min t, max t), as evt2_run's. The GIL is released throughout.
 */
static PyObject *
dat_run(PyObject *self, PyObject *args)
{
    Py_buffer wb, sb, tb, xb, yb, pb;
    long long width, height;
    int decode, outcome = E3_OK;
    int64_t n = 0, bad = -1, t_min = (int64_t)1 << 62, t_max = -((int64_t)1 << 62);
    const char *fault = NULL;

    (void)self;
    if (!PyArg_ParseTuple(args, "y*w*LLpw*w*w*w*", &wb, &sb, &width, &height, &decode, &tb, &xb, &yb, &pb))
        return NULL;
    const uint32_t *words = (const uint32_t *)wb.buf;
    int64_t *state = (int64_t *)sb.buf, *t = (int64_t *)tb.buf;
    uint16_t *x = (uint16_t *)xb.buf, *y = (uint16_t *)yb.buf;
    uint8_t *p = (uint8_t *)pb.buf;
    int64_t n_events = wb.len / 8, cap = tb.len / 8;

    static const int64_t lod[2] = {-1, 0}, hid[2] = {(int64_t)1 << 32, STATE_MOST}; /* last stamp, epoch */
    if (sb.len != 2 * 8)
        fault = "the state is two int64";
    else if (!state_in(state, lod, hid, 2))
        fault = "a state DAT events cannot leave";
    else if (width < 0 || width > SENSOR_MOST || height < 0 || height > SENSOR_MOST)
        fault = "the sensor's width and height are 0 to 65536";
    else if (xb.len / 2 != cap || yb.len / 2 != cap || pb.len != cap)
        fault = "the columns differ in length";
    if (fault == NULL) {
        Py_BEGIN_ALLOW_THREADS
        int64_t prev = state[0], epoch = state[1];
        int64_t i = 0;
        for (; i < n_events; i++) {
            int64_t stamp = words[2 * i];
            uint32_t d = words[2 * i + 1], xx = d & 0x3FFF, yy = (d >> 14) & 0x3FFF;
            if (decode && n >= cap) { outcome = E3_FULL; break; }
            if (stamp < prev && prev - stamp > ((int64_t)1 << 31))
                epoch++;
            prev = stamp;
            if (xx >= width || yy >= height) { outcome = E3_COORD; break; }
            int64_t now = (int64_t)(((uint64_t)epoch << 32) | (uint64_t)stamp);
            if (decode) {
                t[n] = now;
                x[n] = (uint16_t)xx;
                y[n] = (uint16_t)yy;
                p[n] = (d >> 28) != 0;
            }
            t_min = now < t_min ? now : t_min;
            t_max = now > t_max ? now : t_max;
            n++;
        }
        bad = outcome == E3_OK ? -1 : i;
        state[0] = prev, state[1] = epoch;
        Py_END_ALLOW_THREADS
    }
    Py_buffer *const bufs[] = {&wb, &sb, &tb, &xb, &yb, &pb};
    return decoded(bufs, 6, fault, n, 0, outcome, bad, t_min, t_max);
}

/* es_run(data, state, width, height, decode, atis, t, x, y, p)
 *
 * Event Stream 2.x bytes, DVS or (atis) ATIS, taken one after another from state (six int64, updated in place: the
 * time, the position inside an event (0: at its first byte, to 4), x, y, the flags (DVS: the polarity; ATIS: the
 * polarity in bit 1, the threshold-crossing flag in bit 0), and the ATIS threshold crossings left out so far), to
 * the results of evtk.io.prophesee.decoders' _es_dvs_run and _es_atis_run:
 *   DVS: 0xFF adds 127 us, 0xFE is a reset; any other first byte adds its top seven bits to the time, its bit 0
 *   the polarity. ATIS: 0xFC is a reset, 0xFD to 0xFF add 63 us times their two low bits; any other first byte
 *   adds its top six bits to the time, with the flags in its two low bits. Four bytes follow: x, then y counted
 *   from the bottom row (uint16 each, little-endian); the event's row is height - 1 - y. An ATIS threshold
 *   crossing is checked against the sensor, counted and left out.
 *
 * Stops at an event off the width x height sensor (E3_COORD, at the event's last byte; the time, position and
 * count are kept, the rest of the state not, as the loops do). Decoding, the columns must hold len(data) / 5 + 1
 * events (every event a call can end: the one the state began, then one every five bytes). Returns (events, 0,
 * outcome, index of the byte stopped at or -1, min t, max t of the events; 2**62 and -2**62 without events). The
 * GIL is released throughout.
 */
static PyObject *
es_run(PyObject *self, PyObject *args)
{
    Py_buffer db, sb, tb, xb, yb, pb;
    long long width, height;
    int decode, atis, outcome = E3_OK;
    int64_t n = 0, bad = -1, t_min = (int64_t)1 << 62, t_max = -((int64_t)1 << 62);
    const char *fault = NULL;
    /* time, position, x, y, flags, threshold crossings left out */
    static const int64_t lo[6] = {0, 0, 0, 0, 0, 0};
    static const int64_t hi[6] = {(int64_t)1 << 62, 5, SENSOR_MOST, SENSOR_MOST, 4, (int64_t)1 << 62};

    (void)self;
    if (!PyArg_ParseTuple(args, "y*w*LLppw*w*w*w*", &db, &sb, &width, &height, &decode, &atis, &tb, &xb, &yb, &pb))
        return NULL;
    const uint8_t *data = (const uint8_t *)db.buf;
    int64_t *state = (int64_t *)sb.buf, *t = (int64_t *)tb.buf;
    uint16_t *x = (uint16_t *)xb.buf, *y = (uint16_t *)yb.buf;
    uint8_t *p = (uint8_t *)pb.buf;
    int64_t n_bytes = db.len, cap = tb.len / 8;

    if (sb.len != 6 * 8)
        fault = "the state is six int64";
    else if (!state_in(state, lo, hi, 6))
        fault = "a state Event Stream bytes cannot leave";
    else if (width < 0 || width > SENSOR_MOST || height < 0 || height > SENSOR_MOST)
        fault = "the sensor's width and height are 0 to 65536";
    else if (xb.len / 2 != cap || yb.len / 2 != cap || pb.len != cap)
        fault = "the columns differ in length";
    else if (decode && cap < n_bytes / 5 + 1)
        fault = "the columns hold fewer events than the bytes can end";
    if (fault == NULL) {
        Py_BEGIN_ALLOW_THREADS
        int64_t tc = state[0], phase = state[1], xi = state[2], yi = state[3], flags = state[4], left = state[5];
        int64_t i = 0;
        for (; i < n_bytes; i++) {
            int64_t b = data[i];
            if (phase == 0) {
                if (atis) {
                    if (b >= 0xFC) {
                        tc += 63 * (b & 3);
                        continue;
                    }
                    tc += b >> 2;
                    flags = b & 3;
                } else {
                    if (b >= 0xFE) {
                        tc += b == 0xFF ? 127 : 0;
                        continue;
                    }
                    tc += b >> 1;
                    flags = b & 1;
                }
                if (n_bytes - i < 5) { /* the event's last bytes are in the next call's data */
                    phase = 1;
                    continue;
                }
                /* its four bytes at once (what the positions below take one at a time), i at its last */
                xi = data[i + 1] | (int64_t)data[i + 2] << 8;
                yi = data[i + 3] | (int64_t)data[i + 4] << 8;
                i += 4;
            } else if (phase == 1) {
                xi = b;
                phase = 2;
                continue;
            } else if (phase == 2) {
                xi |= b << 8;
                phase = 3;
                continue;
            } else if (phase == 3) {
                yi = b;
                phase = 4;
                continue;
            } else {
                yi |= b << 8;
                phase = 0;
            }
            /* an event's last byte */
            if (xi >= width || yi >= height) {
                outcome = E3_COORD;
                break;
            }
            if (atis && (flags & 1)) {
                left++;
                continue;
            }
            if (decode) {
                t[n] = tc;
                x[n] = (uint16_t)xi;
                y[n] = (uint16_t)(height - 1 - yi);
                p[n] = (uint8_t)(atis ? flags >> 1 : flags);
            }
            n++;
            t_min = tc < t_min ? tc : t_min;
            t_max = tc > t_max ? tc : t_max;
        }
        bad = outcome == E3_OK ? -1 : i;
        state[0] = tc, state[1] = phase, state[5] = left;
        if (outcome == E3_OK)
            state[2] = xi, state[3] = yi, state[4] = flags;
        Py_END_ALLOW_THREADS
    }
    Py_buffer *const bufs[] = {&db, &sb, &tb, &xb, &yb, &pb};
    return decoded(bufs, 6, fault, n, 0, outcome, bad, t_min, t_max);
}

/* evt2_scan(words), dat_scan(words)
 *
 * The counts of EVT 2.0 words (CD events, triggers; up to the first word of no type, whose index is the third
 * result, -1 if none) or DAT events (pairs of uint32; no triggers, no types), without decoding them, and their
 * effect on the decoder's state: the first and the last time high (EVT 2.0: bits 0..27 of the EV_TIME_HIGH words)
 * or time stamp (DAT), -1 without any, and the wraps between them (a drop of more than 2**27 or 2**31). Events off
 * any sensor are counted (the decoder finds them). The GIL is released.
 */
static PyObject *
evt2_scan(PyObject *self, PyObject *args)
{
    Py_buffer wb;

    (void)self;
    if (!PyArg_ParseTuple(args, "y*", &wb))
        return NULL;
    const uint32_t *words = (const uint32_t *)wb.buf;
    int64_t n_words = wb.len / 4, n_ev = 0, n_tr = 0, stop = -1, first = -1, last = -1, wraps = 0;
    Py_BEGIN_ALLOW_THREADS
    for (int64_t i = 0; i < n_words; i++) {
        uint32_t w = words[i];
        unsigned kind = w >> 28;
        n_ev += kind <= 1;
        n_tr += kind == 10;
        if (kind == 8) {
            int64_t v = w & 0xFFFFFFF;
            wraps += last >= 0 && v < last && last - v > ((int64_t)1 << 27);
            first = first < 0 ? v : first;
            last = v;
        } else if (kind > 1 && kind != 10 && kind < 14) {
            stop = i;
            break;
        }
    }
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&wb);
    return Py_BuildValue("LLL(LLL)", (long long)n_ev, (long long)n_tr, (long long)stop, (long long)first,
                         (long long)last, (long long)wraps);
}

static PyObject *
dat_scan(PyObject *self, PyObject *args)
{
    Py_buffer wb;

    (void)self;
    if (!PyArg_ParseTuple(args, "y*", &wb))
        return NULL;
    const uint32_t *words = (const uint32_t *)wb.buf;
    int64_t n_ev = wb.len / 8, first = -1, last = -1, wraps = 0;
    Py_BEGIN_ALLOW_THREADS
    if (n_ev > 0)
        first = last = words[0];
    for (int64_t i = 1; i < n_ev; i++) {
        int64_t v = words[2 * i];
        wraps += v < last && last - v > ((int64_t)1 << 31);
        last = v;
    }
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&wb);
    return Py_BuildValue("LLL(LLL)", (long long)n_ev, 0LL, -1LL, (long long)first, (long long)last,
                         (long long)wraps);
}

/* The first index of the sorted t[0 .. n - 1] at or after v (numpy's searchsorted, side "left"). */
static int64_t
lower_bound(const int64_t *t, int64_t n, int64_t v)
{
    int64_t lo = 0, hi = n;
    while (lo < hi) {
        int64_t mid = lo + (hi - lo) / 2;
        if (t[mid] < v)
            lo = mid + 1;
        else
            hi = mid;
    }
    return lo;
}

/* One window's events t[lo .. hi - 1] into its frames: the region's pixel k = (y - y0) * w_px + (x - x0) of the OFF
 * frame (counts[base + k]) or the ON one (counts[plane + base + k]); with times (first, last not NULL), the first
 * and last ON event's time from the window's start a_us. Returns the events inside the region. */
NOINLINE static int64_t
timed_window(const int64_t *restrict t, const uint16_t *restrict x, const uint16_t *restrict y,
             const uint8_t *restrict p, int64_t lo, int64_t hi, int64_t x0, int64_t w_px, int64_t y0, int64_t h_px,
             int64_t base, int64_t plane, int64_t a_us, int32_t *restrict counts, int32_t *restrict first,
             int32_t *restrict last)
{
    int64_t used = 0;
    for (int64_t i = lo; i < hi; i++) {
        /* unsigned: coordinates below the region's corner wrap past its far edge, one compare each */
        uint64_t xi = (uint64_t)((int64_t)x[i] - x0), yi = (uint64_t)((int64_t)y[i] - y0);
        if (xi >= (uint64_t)w_px || yi >= (uint64_t)h_px)
            continue;
        int64_t k = base + (int64_t)yi * w_px + (int64_t)xi;
        int on = p[i] != 0;
        int32_t *bin = counts + k + (on ? plane : 0);
        *bin = (int32_t)((uint32_t)*bin + 1u); /* (the caller refuses a window past 2**31 - 1 events) */
        used++;
        if (first != NULL && on) {
            /* windows shorter than 2**31 us (checked by the caller); the difference wraps, as numba's and numpy's */
            int32_t dt = (int32_t)(uint32_t)((uint64_t)t[i] - (uint64_t)a_us);
            if (first[k] < 0)
                first[k] = dt;
            last[k] = dt;
        }
    }
    return used;
}

/* accumulate_chunk(t, x, y, p, starts, ends, x0, x1, y0, y1, counts, total, started, first, last, wa, wz)
 *
 * evtk.reconstruct.accumulate._accumulate_chunk for windows wa .. wz - 1: a chunk of time-sorted events (t int64, x
 * and y uint16, p uint8, one length) added to every window [starts[w], ends[w]) it meets (int64, one per window).
 * counts: int32, OFF then ON, (2, windows, y1 - y0, x1 - x0) flat; total: int64 events per window so far; started:
 * one byte per window, the windows whose frames (and times) have been zeroed (set on the first chunk that meets
 * them); first, last: int32 (windows, y1 - y0, x1 - x0) flat, the first and last ON event's time from its window's
 * start (-1: none), or both empty for no times. Calls on other window ranges may run at the same time. Returns the
 * events counted inside the region; raises ValueError for an argument this file refuses (the wrapper's checks
 * make that a bug).
 */
static PyObject *
accumulate_chunk(PyObject *self, PyObject *args)
{
    Py_buffer tb, xb, yb, pb, sb, eb, cb, totb, stb, fb, lb;
    long long x0, x1, y0, y1, wa, wz;
    const char *fault = NULL;
    int64_t used = 0;

    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*LLLLw*w*w*w*w*LL", &tb, &xb, &yb, &pb, &sb, &eb, &x0, &x1, &y0, &y1,
                          &cb, &totb, &stb, &fb, &lb, &wa, &wz))
        return NULL;
    int64_t n = tb.len / 8, n_w = sb.len / 8;
    /* the region's bounds checked before any arithmetic on them */
    int region_ok = x0 >= 0 && y0 >= 0 && x0 < x1 && y0 < y1 && x1 <= 65536 && y1 <= 65536;
    int64_t w_px = region_ok ? x1 - x0 : 1, h_px = region_ok ? y1 - y0 : 1;
    if (xb.len / 2 < n || yb.len / 2 < n || pb.len < n || eb.len / 8 != n_w)
        fault = "columns or windows of two lengths";
    else if (!region_ok)
        fault = "a region off the coordinates";
    else if (n_w > 0 && (cb.len / 4 / 2 / n_w / h_px / w_px < 1 || totb.len / 8 < n_w || stb.len < n_w))
        fault = "counts, totals or flags shorter than the windows";
    else if (fb.len != lb.len || (fb.len > 0 && n_w > 0 && fb.len / 4 / n_w / h_px / w_px < 1))
        fault = "times shorter than the counts";
    else if (wa < 0 || wz < wa || wz > n_w)
        fault = "windows outside the starts";
    if (fault == NULL && n > 0) {
        const int64_t *t = (const int64_t *)tb.buf, *starts = (const int64_t *)sb.buf, *ends = (const int64_t *)eb.buf;
        int32_t *counts = (int32_t *)cb.buf, *first = fb.len ? (int32_t *)fb.buf : NULL;
        int32_t *last = lb.len ? (int32_t *)lb.buf : NULL;
        int64_t *total = (int64_t *)totb.buf;
        char *started = (char *)stb.buf;
        int64_t frame = h_px * w_px, plane = n_w * frame;
        Py_BEGIN_ALLOW_THREADS
        for (int64_t w = wa; w < wz; w++) {
            int64_t a = starts[w], b = ends[w];
            if (b <= t[0] || a > t[n - 1])
                continue;
            int64_t lo = lower_bound(t, n, a), hi = lower_bound(t, n, b);
            total[w] = (int64_t)((uint64_t)total[w] + (uint64_t)(hi - lo)); /* wraps, as numba's int64 */
            int64_t base = w * frame;
            if (!started[w]) {
                memset(counts + base, 0, (size_t)frame * sizeof(int32_t));
                memset(counts + plane + base, 0, (size_t)frame * sizeof(int32_t));
                if (first != NULL) {
                    memset(first + base, 0xFF, (size_t)frame * sizeof(int32_t)); /* -1 */
                    memset(last + base, 0xFF, (size_t)frame * sizeof(int32_t));
                }
                started[w] = 1;
            }
            used += timed_window(t, (const uint16_t *)xb.buf, (const uint16_t *)yb.buf, (const uint8_t *)pb.buf, lo,
                                 hi, x0, w_px, y0, h_px, base, plane, a, counts, first, last);
        }
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&tb);
    PyBuffer_Release(&xb);
    PyBuffer_Release(&yb);
    PyBuffer_Release(&pb);
    PyBuffer_Release(&sb);
    PyBuffer_Release(&eb);
    PyBuffer_Release(&cb);
    PyBuffer_Release(&totb);
    PyBuffer_Release(&stb);
    PyBuffer_Release(&fb);
    PyBuffer_Release(&lb);
    if (fault != NULL) {
        PyErr_SetString(PyExc_ValueError, fault);
        return NULL;
    }
    return PyLong_FromLongLong((long long)used);
}

/* The timing linearisation's solve (evtk.reconstruct.timing): numba's scalar kernel _timing_solve_jit in C, the
 * same operations in the same order, so that a fresh process solves without loading numba and without numpy's
 * many short calls. */

/* u / theta for a pixel whose n >= 2 ON events after a step came first at a_us and last at b_us after it, the light
 * exp(log_rate) photoelectrons/s; -1 where no noise-free chain gives those times (timing._timing_factor). */
static double
timing_factor(int64_t n, double a_us, double b_us, double log_rate, double tau_min_us, double tau_electrons,
              double refr_us)
{
    double tau = tau_min_us + tau_electrons / (exp(log_rate) * 1e-6);
    double r = refr_us / tau;
    double m_r = (double)(n - 1) * r;
    double x = (b_us - a_us) / tau - m_r;
    if (!(x > 0.0))
        return -1.0;
    double big = b_us / tau;
    if (big < 700.0)
        return -expm1(-m_r) / (-expm1(-r) * exp(-big) * expm1(x));
    double log_den = log(-expm1(-r)) - big + x + log1p(-exp(-x)); /* where exp(-big) would underflow */
    return exp(log(-expm1(-m_r)) - log_den);
}

/* Windows ya .. yb - 1 (rows of n_px pairs): secant steps from the middle of the band the count allows, then the
 * Illinois method within the band; NaN where the times do not determine the step. */
static void
timing_rows(const int64_t *n_on, const int64_t *first, const int64_t *last, const double *theta, double theta_nominal,
            const double *band_lo, const double *band_hi, int64_t top, double offset_us, double log_blank,
            double tau_min_us, double tau_electrons, double refr_us, int64_t n_px, int64_t ya, int64_t yb, double *out)
{
    for (int64_t j = ya * n_px; j < yb * n_px; j++) {
        int64_t n = n_on[j], i = j % n_px;
        out[j] = Py_NAN;
        if (n < 2 || first[j] < 0 || last[j] < first[j])
            continue;
        double a = (double)first[j] + offset_us + 0.5; /* time stamps are whole us, rounded down */
        double b = (double)last[j] + offset_us + 0.5;
        double th = theta[i], s = th / theta_nominal;
        double lo = band_lo[n < top ? n : top] * s - th;
        lo = lo > 0.0 ? lo : 0.0;
        double hi = n < top - 1 ? band_hi[n + 1] * s + th : band_hi[top] * (s > 1.0 ? s : 1.0) + th;
        double u0 = 0.5 * (lo + hi);
        double f = timing_factor(n, a, b, log_blank + u0, tau_min_us, tau_electrons, refr_us);
        if (f < 0.0) /* depends on the times only */
            continue;
        double h0 = u0 - th * f, u1 = th * f;
        int done = 0;
        for (int k = 0; k < 10; k++) {
            double h1 = u1 - th * timing_factor(n, a, b, log_blank + u1, tau_min_us, tau_electrons, refr_us);
            if (fabs(h1) <= 1e-4 * (1.0 + fabs(u1))) {
                done = lo <= u1 && u1 <= hi;
                break;
            }
            if (h1 == h0)
                break;
            double step = u1 - h1 * (u1 - u0) / (h1 - h0);
            u0 = u1;
            h0 = h1;
            u1 = step;
            if (!(-1.0 < u1 && u1 < 2.0 * hi + 1.0))
                break;
        }
        if (done) {
            out[j] = u1;
            continue;
        }
        double h_lo = lo - th * timing_factor(n, a, b, log_blank + lo, tau_min_us, tau_electrons, refr_us);
        double h_hi = hi - th * timing_factor(n, a, b, log_blank + hi, tau_min_us, tau_electrons, refr_us);
        if (!(h_lo < 0.0 && 0.0 < h_hi))
            continue;
        int side = 0;
        double u = lo;
        for (int k = 0; k < 100; k++) {
            u = (lo * h_hi - hi * h_lo) / (h_hi - h_lo);
            double h = u - th * timing_factor(n, a, b, log_blank + u, tau_min_us, tau_electrons, refr_us);
            if (fabs(h) <= 1e-6 * (1.0 + u) || hi - lo <= 1e-9)
                break;
            if (h > 0.0) {
                hi = u;
                h_hi = h;
                if (side == 1)
                    h_lo *= 0.5;
                side = 1;
            } else {
                lo = u;
                h_lo = h;
                if (side == -1)
                    h_hi *= 0.5;
                side = -1;
            }
        }
        out[j] = u;
    }
}

/* timing_solve(n_on, first, last, theta, band_lo, band_hi, out, n_px, ya, yb, theta_nominal, offset_us, log_blank,
 *              tau_min_us, tau_electrons, refr_us)
 *
 * n_on, first, last: int64, rows of n_px (window, pixel) pairs; theta: float64, n_px; band_lo, band_hi: float64 of
 * one length (at least 1); out: float64 like n_on. Rows ya .. yb - 1 of out are set (other calls may set other
 * rows at the same time). Raises ValueError for an argument this file refuses (the wrapper's checks make that a
 * bug).
 */
static PyObject *
timing_solve(PyObject *self, PyObject *args)
{
    Py_buffer nb, fb, lb, tb, lob, hib, ob;
    long long n_px, ya, yb;
    double theta_nominal, offset_us, log_blank, tau_min_us, tau_electrons, refr_us;
    const char *fault = NULL;

    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*w*LLLdddddd", &nb, &fb, &lb, &tb, &lob, &hib, &ob, &n_px, &ya, &yb,
                          &theta_nominal, &offset_us, &log_blank, &tau_min_us, &tau_electrons, &refr_us))
        return NULL;
    Py_ssize_t pairs = nb.len / 8;
    if (n_px <= 0 || ya < 0 || yb < ya || yb > pairs / n_px)
        fault = "rows outside the counts";
    else if (fb.len / 8 < pairs || lb.len / 8 < pairs || ob.len / 8 < pairs || tb.len / 8 < n_px)
        fault = "times, thresholds or out shorter than the counts";
    else if (lob.len < 8 || lob.len != hib.len)
        fault = "bands empty or of two lengths";
    if (fault == NULL && yb > ya) {
        Py_BEGIN_ALLOW_THREADS
        timing_rows((const int64_t *)nb.buf, (const int64_t *)fb.buf, (const int64_t *)lb.buf, (const double *)tb.buf,
                    theta_nominal, (const double *)lob.buf, (const double *)hib.buf, lob.len / 8 - 1, offset_us,
                    log_blank, tau_min_us, tau_electrons, refr_us, n_px, ya, yb, (double *)ob.buf);
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&nb);
    PyBuffer_Release(&fb);
    PyBuffer_Release(&lb);
    PyBuffer_Release(&tb);
    PyBuffer_Release(&lob);
    PyBuffer_Release(&hib);
    PyBuffer_Release(&ob);
    if (fault != NULL) {
        PyErr_SetString(PyExc_ValueError, fault);
        return NULL;
    }
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"count_windows", count_windows, METH_VARARGS,
     "Count events into their windows' bins with the GIL released (see evtk._native.count_windows)."},
    {"net_sums", net_sums, METH_VARARGS,
     "Sum windows' net counts per pixel and per block with the GIL released (see evtk._native.net_sums)."},
    {"decode_lz4_batch", decode_lz4_batch, METH_VARARGS,
     "Decode a batch of LZ4 event packets with the GIL released (see evtk._native.decode_lz4_batch)."},
    {"decode_lz4_range", decode_lz4_range, METH_VARARGS,
     "Read and decode the batches of a range of LZ4 or Zstandard event packets with the GIL released (see "
     "evtk._native.decode_lz4_range)."},
    {"evt3_run", evt3_run, METH_VARARGS,
     "Decode or count EVT 3.0 words with the GIL released (see evtk._native.evt3_run)."},
    {"evt3_scan", evt3_scan, METH_VARARGS,
     "Count EVT 3.0 words and sum up their effect, the GIL released (see evtk._native.prophesee_scan)."},
    {"evt2_run", evt2_run, METH_VARARGS,
     "Decode or count EVT 2.0 words with the GIL released (see evtk._native.evt2_run)."},
    {"dat_run", dat_run, METH_VARARGS,
     "Decode or count DAT events with the GIL released (see evtk._native.dat_run)."},
    {"es_run", es_run, METH_VARARGS,
     "Decode or count Event Stream DVS or ATIS bytes with the GIL released (see evtk._native.es_run)."},
    {"evt2_scan", evt2_scan, METH_VARARGS,
     "Count EVT 2.0 words and sum up their effect, the GIL released (see evtk._native.prophesee_scan)."},
    {"dat_scan", dat_scan, METH_VARARGS,
     "Count DAT events and sum up their effect, the GIL released (see evtk._native.prophesee_scan)."},
    {"accumulate_chunk", accumulate_chunk, METH_VARARGS,
     "Count a chunk of events into the windows it meets, with ON-event times, the GIL released (see "
     "evtk._native.accumulate_chunk)."},
    {"timing_solve", timing_solve, METH_VARARGS,
     "Solve the timing linearisation's steps with the GIL released (see evtk._native.timing_solve)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_ckernels", "evtk's compiled counting kernels (optional).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC
PyInit__ckernels(void)
{
    fill_pop12();
    PyObject *m = PyModule_Create(&module);
    /* the codecs decode_lz4_range takes (its optional codec argument): a build before Zstandard has no such name */
    /* count_windows takes the windows to clear (zero_from, zero_to): a build before it has no such name */
    if (m != NULL && (PyModule_AddIntConstant(m, "RANGE_CODECS", 2) < 0
                      || PyModule_AddIntConstant(m, "COUNT_CLEARS", 1) < 0)) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
