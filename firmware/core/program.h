/* Program store of one valve: a byte ring holding queued valve programs in icefab.flow's
 * binary layout (PROTOCOL.md 5, PROG_DATA), the upload validator and the play reader.
 * Portable C99, no hardware access. Thesis 2.3.1: uint16 pulse instants of 2 ms ticks,
 * at most 16 384 entries and 131.072 s per piece. */
#ifndef VC_PROGRAM_H
#define VC_PROGRAM_H

#include <stdint.h>
#include "protocol.h"

/* Upload validator: checks the layout byte by byte as it arrives. */
enum { VC_DEC_HEADER = 0, VC_DEC_PIECE = 1, VC_DEC_TICKS = 2, VC_DEC_WIDTHS = 3,
       VC_DEC_DONE = 4 };

typedef struct {
    uint8_t phase;
    uint8_t mode;          /* 0 FM, 1 PWM */
    uint8_t nacc;          /* bytes gathered in acc */
    uint8_t acc[16];
    uint32_t pos;          /* bytes consumed */
    uint32_t pieces_left;
    uint32_t n;            /* pulses of the current piece */
    uint32_t i;            /* entries of the current array consumed */
    uint32_t dur_us;
    uint16_t last_tick;
    uint32_t pulses;       /* pulses decoded (all pieces) */
    uint64_t total_us;     /* sum of the piece durations decoded */
} vc_dec;

void vc_dec_init(vc_dec *d);
/* Feed one byte; 0 if fine, else -1 (the violation is at byte d->pos). */
int vc_dec_byte(vc_dec *d, uint8_t b);

/* One queued program. */
typedef struct {
    uint32_t total;        /* bytes announced */
    uint32_t received;
    uint16_t crc;          /* CRC-16/CCITT-FALSE of the bytes received */
    uint8_t complete;
    uint8_t locked;        /* armed or playing: cannot be replaced */
    uint32_t ticks;        /* complete: its length, vc_ticks_round(dec.total_us) (computed
                              by cmd_data unlocked, stored with the commit, locked) */
    vc_dec dec;
} vc_prog;

/* Play reader over the head program's bytes in the ring. */
enum { VC_RD_HEADER = 0, VC_RD_PIECE = 1, VC_RD_PULSES = 2, VC_RD_END = 3 };
enum { VC_STEP_PULSE = 0, VC_STEP_NEED = 1, VC_STEP_END = 2 };

typedef struct {
    uint8_t phase;
    uint8_t mode;
    uint8_t have_next;
    uint32_t consumed;     /* bytes of the program consumed (read and freed) */
    uint32_t pieces_left;
    uint32_t n, i;         /* pulses of the current piece, pulses read */
    uint32_t due_tick;     /* VC_STEP_NEED: the earliest play tick the missing bytes'
                              pulse can be due (an underrun only from then on) */
    uint16_t last_rel;     /* tick of the last pulse read, from its piece's start */
    uint64_t start_us;     /* start of the current piece, us from the play start */
    uint64_t total_us;     /* start of the next piece */
    uint32_t piece_tick;   /* S_j, ticks */
    uint32_t next_tick;    /* play tick of the next pulse */
    uint16_t next_width;   /* PWM width, us (FM: 0) */
    uint32_t end_tick;     /* valid at VC_RD_END */
    uint32_t emitted;
} vc_reader;

typedef struct {
    uint8_t buf[VC_STORE_BYTES];
    uint32_t r, w, used;       /* ring read/write index, bytes held */
    vc_prog progs[VC_QUEUE];   /* FIFO: progs[(head + k) % VC_QUEUE] */
    uint8_t head, count;
    uint16_t pulse_us;         /* FM pulse width (CONFIG) */
    vc_reader rd;              /* reader of the head program while playing */
} vc_store;

void vc_store_init(vc_store *s);
uint32_t vc_store_free(const vc_store *s);
vc_prog *vc_store_tail(vc_store *s);            /* last queued program or 0 */
vc_prog *vc_store_at(vc_store *s, unsigned k);  /* k-th queued program or 0 */
void vc_store_clear(vc_store *s);               /* drop every program and byte */
int vc_store_begin(vc_store *s, uint32_t total); /* 0, or -1 queue full */
void vc_store_drop_tail(vc_store *s);           /* remove the last program and its bytes */
/* Appending n bytes to the tail program p, in three steps so that the long ones can run
 * while the tick may interrupt (valvectl.c, cmd_data). vc_store_check: validate them on d,
 * a copy of p->dec; 0, or -1 (-2: NO_ROOM) with *bad = the program byte offset of the
 * violation; writes nothing but *d, *bad. vc_store_put: copy them into the free ring space
 * from w (the store's w when checked; room checked by the caller); no index moves.
 * vc_store_commit: make them the tail's (w, used, decoder d, CRC crc, received). */
int vc_store_check(const vc_prog *p, const uint8_t *data, uint32_t n, vc_dec *d,
                   uint32_t *bad);
void vc_store_put(vc_store *s, uint32_t w, const uint8_t *data, uint32_t n);
void vc_store_commit(vc_store *s, const vc_dec *d, uint16_t crc, uint32_t n);
void vc_store_pop(vc_store *s);                 /* remove the head program (played) */

/* Play reader: start on the head program; step to the next pulse. */
void vc_reader_start(vc_store *s);
int vc_reader_step(vc_store *s);                /* VC_STEP_* */

uint32_t vc_ticks_round(uint64_t us);           /* floor(us / tick + 1/2) */

#endif
