/* Program store, upload validator and play reader: see program.h. */
#include <string.h>
#include "program.h"
#include "crc16.h"

static uint32_t le32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
           ((uint32_t)p[3] << 24);
}

/* Below 2^32 us (71.6 minutes) in 32 bits: a multiply. The 64-bit division is libgcc's
 * loop on the LPC2148, ~500 cycles, and ARM (two of them) runs with the tick locked out. */
uint32_t vc_ticks_round(uint64_t us)
{
    if (us < 0xFFFFFFFFu - VC_TICK_US) return ((uint32_t)us + VC_TICK_US / 2u) / VC_TICK_US;
    return (uint32_t)((us + VC_TICK_US / 2u) / VC_TICK_US);
}

/* ------------------------------------------------------------------ upload validator */

/* Field by field, acc aside (each byte of it is written before it is read): PROG_BEGIN
 * runs with the tick locked out, and zeroing the 72-byte program slot there was most of
 * its work (make rx-work). */
void vc_dec_init(vc_dec *d)
{
    d->phase = VC_DEC_HEADER;
    d->mode = d->nacc = 0;
    d->pos = d->pieces_left = d->n = d->i = d->dur_us = d->pulses = 0;
    d->last_tick = 0;
    d->total_us = 0;
}

static void piece_done(vc_dec *d)
{
    d->pieces_left--;
    d->phase = d->pieces_left ? VC_DEC_PIECE : VC_DEC_DONE;
    d->nacc = 0;
}

/* 0 fine; -1 layout or limit violated (PROGRAM); -2 a PWM piece larger than the store
 * (NO_ROOM). The violation is at byte d->pos (d->pos is advanced only on success). */
int vc_dec_byte(vc_dec *d, uint8_t b)
{
    switch (d->phase) {
    case VC_DEC_HEADER:
        d->acc[d->nacc++] = b;
        switch (d->nacc) {
        case 1: if (b != 'I') return -1; break;
        case 2: if (b != 'C') return -1; break;
        case 3: if (b != 'E') return -1; break;
        case 4: if (b != 'V') return -1; break;
        case 6: if (d->acc[4] != 1 || d->acc[5] != 0) return -1; break;  /* version 1 */
        case 7: if (b > 1) return -1; d->mode = b; break;                /* FM / PWM */
        case 8: if (b != 0) return -1; break;                            /* reserved */
        case 12: if (le32(d->acc + 8) != VC_TICK_US) return -1; break;   /* our tick */
        case 16:
            d->pieces_left = le32(d->acc + 12);
            if (d->pieces_left == 0) return -1;
            d->phase = VC_DEC_PIECE;
            d->nacc = 0;
            break;
        default: break;
        }
        break;
    case VC_DEC_PIECE:
        d->acc[d->nacc++] = b;
        if (d->nacc == 4) {
            d->n = le32(d->acc);
            if (d->n > VC_MAX_PULSES) return -1;            /* thesis 2.3.1: 16 384 */
            /* PWM: a pulse needs its tick and width (2 n + 2 bytes on from its tick),
             * and a piece's widths go only at its end: piece after piece without a
             * gap, 2 n_j + 8 + 2 n_j+1 + 2 <= the store, which 4 n + 10 keeps */
            if (d->mode == 1 && 4u * d->n + 10u > VC_STORE_BYTES) return -2;
        } else if (d->nacc == 8) {
            d->dur_us = le32(d->acc + 4);
            if (d->dur_us > VC_MAX_PIECE_US) return -1;     /* thesis 2.3.1: 131.072 s */
            d->total_us += d->dur_us;
            d->i = 0;
            d->nacc = 0;
            if (d->n == 0) piece_done(d);
            else d->phase = VC_DEC_TICKS;
        }
        break;
    case VC_DEC_TICKS:
        d->acc[d->nacc++] = b;
        if (d->nacc == 2) {
            uint16_t t = (uint16_t)(d->acc[0] | (d->acc[1] << 8));
            if (d->i > 0 && t < d->last_tick) return -1;    /* non-decreasing */
            if ((uint32_t)t * VC_TICK_US > d->dur_us + VC_TICK_US) return -1;
            d->last_tick = t;
            d->nacc = 0;
            d->pulses++;
            if (++d->i == d->n) {
                d->i = 0;
                if (d->mode == 1) d->phase = VC_DEC_WIDTHS;
                else piece_done(d);
            }
        }
        break;
    case VC_DEC_WIDTHS:
        d->acc[d->nacc++] = b;
        if (d->nacc == 2) {
            if (d->acc[0] == 0 && d->acc[1] == 0) return -1;   /* width 0: no pulse */
            d->nacc = 0;
            if (++d->i == d->n) piece_done(d);
        }
        break;
    default:
        return -1;                                          /* bytes after the last piece */
    }
    d->pos++;
    return 0;
}

/* ------------------------------------------------------------------ store */

void vc_store_init(vc_store *s)
{
    memset(s, 0, sizeof *s);
    s->pulse_us = VC_DEFAULT_PULSE_US;
}

/* Indices only: a program slot is cleared when it is begun, the reader when a play starts,
 * and ring bytes are read only below a program's received count. Zeroing the whole store
 * (12 kB a valve) held interrupts off ~2 ms on the board at ABORT, and a FAULT did it in
 * the tick interrupt. */
void vc_store_clear(vc_store *s)
{
    s->r = s->w = s->used = 0;
    s->head = s->count = 0;
}

uint32_t vc_store_free(const vc_store *s)
{
    return VC_STORE_BYTES - s->used;
}

vc_prog *vc_store_at(vc_store *s, unsigned k)
{
    if (k >= s->count) return 0;
    return &s->progs[(s->head + k) % VC_QUEUE];
}

vc_prog *vc_store_tail(vc_store *s)
{
    return s->count ? vc_store_at(s, s->count - 1u) : 0;
}

int vc_store_begin(vc_store *s, uint32_t total)
{
    vc_prog *p;
    if (s->count >= VC_QUEUE) return -1;
    p = &s->progs[(s->head + s->count) % VC_QUEUE];
    p->total = total;
    p->received = 0;
    p->crc = VC_CRC_INIT;
    p->complete = p->locked = 0;
    p->ticks = 0;
    vc_dec_init(&p->dec);
    s->count++;
    return 0;
}

void vc_store_drop_tail(vc_store *s)
{
    vc_prog *p = vc_store_tail(s);
    if (!p) return;
    /* an unlocked tail is not being read: all its bytes are still in the ring */
    s->w = (s->w + VC_STORE_BYTES - p->received) % VC_STORE_BYTES;
    s->used -= p->received;
    s->count--;
}

int vc_store_check(const vc_prog *p, const uint8_t *data, uint32_t n, vc_dec *d,
                   uint32_t *bad)
{
    uint32_t k;
    int rc;
    if (n > p->total - p->received) { *bad = p->total; return -1; }
    for (k = 0; k < n; k++) {
        rc = vc_dec_byte(d, data[k]);
        if (rc) { *bad = d->pos; return rc; }
    }
    if (p->received + n == p->total && d->phase != VC_DEC_DONE) {
        *bad = p->total;                                    /* announced bytes missing */
        return -1;
    }
    if (d->phase == VC_DEC_DONE && p->received + n < p->total) {
        *bad = d->pos;                 /* the layout ends before the announced total: a */
        return -1;                     /* streamed program would play as if complete   */
    }
    return 0;
}

void vc_store_put(vc_store *s, uint32_t w, const uint8_t *data, uint32_t n)
{
    uint32_t first = VC_STORE_BYTES - w;
    if (w >= VC_STORE_BYTES || n > VC_STORE_BYTES) return;
    if (first > n) first = n;
    memcpy(s->buf + w, data, first);
    memcpy(s->buf, data + first, n - first);
}

void vc_store_commit(vc_store *s, const vc_dec *d, uint16_t crc, uint32_t n)
{
    vc_prog *p = vc_store_tail(s);
    if (!p) return;
    s->w = (s->w + n) % VC_STORE_BYTES;
    s->used += n;
    p->dec = *d;
    p->crc = crc;
    p->received += n;
    p->complete = (p->received == p->total);
}

void vc_store_pop(vc_store *s)
{
    if (!s->count) return;
    s->head = (uint8_t)((s->head + 1u) % VC_QUEUE);
    s->count--;
}

/* ------------------------------------------------------------------ play reader */

static uint8_t at(const vc_store *s, uint32_t k)
{
    uint32_t i = s->r + k;
    if (i >= VC_STORE_BYTES) i -= VC_STORE_BYTES;
    return s->buf[i];
}

static uint32_t at32(const vc_store *s, uint32_t k)
{
    return (uint32_t)at(s, k) | ((uint32_t)at(s, k + 1) << 8) |
           ((uint32_t)at(s, k + 2) << 16) | ((uint32_t)at(s, k + 3) << 24);
}

static void consume(vc_store *s, uint32_t k)
{
    s->r = (s->r + k) % VC_STORE_BYTES;
    s->used -= k;
    s->rd.consumed += k;
}

void vc_reader_start(vc_store *s)
{
    memset(&s->rd, 0, sizeof s->rd);
    s->rd.phase = VC_RD_HEADER;
}

int vc_reader_step(vc_store *s)
{
    vc_reader *rd = &s->rd;
    vc_prog *p = vc_store_at(s, 0);
    uint32_t avail, need;
    if (rd->have_next) return VC_STEP_PULSE;
    if (!p) return VC_STEP_END;
    for (;;) {
        avail = p->received - rd->consumed;
        switch (rd->phase) {
        case VC_RD_HEADER:
            rd->due_tick = 0;
            if (avail < 16) return VC_STEP_NEED;
            rd->mode = at(s, 6);
            rd->pieces_left = at32(s, 12);
            consume(s, 16);
            rd->phase = VC_RD_PIECE;
            break;
        case VC_RD_PIECE:
            if (rd->pieces_left == 0) {
                rd->end_tick = vc_ticks_round(rd->total_us);
                rd->phase = VC_RD_END;
                return VC_STEP_END;
            }
            /* the piece's first pulse comes at its start S_j at the earliest */
            rd->due_tick = vc_ticks_round(rd->total_us);
            if (avail < 8) return VC_STEP_NEED;
            rd->n = at32(s, 0);
            rd->start_us = rd->total_us;
            rd->total_us += at32(s, 4);
            rd->piece_tick = vc_ticks_round(rd->start_us);
            rd->i = 0;
            rd->last_rel = 0;
            consume(s, 8);
            rd->phase = VC_RD_PULSES;
            break;
        case VC_RD_PULSES:
            if (rd->i == rd->n) {
                if (rd->mode == 1) consume(s, 2u * rd->n);  /* the piece's widths */
                rd->pieces_left--;
                rd->phase = VC_RD_PIECE;
                break;
            }
            /* tick i, and (PWM) width i 2n bytes after it (n - i ticks, then i widths).
             * Only these: a PWM piece read whole at its start had to be in the store
             * beside the last piece's widths, which go at that piece's end: streamed
             * pieces of over ~2 000 pulses underran however fast the PC sent (a review's
             * finding). Missing bytes are an underrun only once their pulse can be due:
             * ticks never decrease within a piece. */
            need = rd->mode == 1 ? 2u * rd->n + 2u : 2u;
            if (avail < need) {
                rd->due_tick = rd->piece_tick + (avail >= 2u
                    ? (uint32_t)(at(s, 0) | (at(s, 1) << 8)) : rd->last_rel);
                return VC_STEP_NEED;
            }
            rd->last_rel = (uint16_t)(at(s, 0) | (at(s, 1) << 8));
            rd->next_tick = rd->piece_tick + rd->last_rel;
            rd->next_width = rd->mode == 1 ?
                (uint16_t)(at(s, 2u * rd->n) | (at(s, 2u * rd->n + 1u) << 8)) : 0u;
            consume(s, 2);
            rd->i++;
            rd->have_next = 1;
            return VC_STEP_PULSE;
        default:
            return VC_STEP_END;
        }
    }
}
