/* Work of the one vc_rx() call that completes a 247-byte frame: bytes moved (memmove) and
 * bytes summed into CRCs. The board runs the parser with interrupts off, so this is how
 * long a tick, and the pulses it starts, can wait behind a frame (about 9 cycles per byte
 * moved and 97 per byte summed at 48 MHz; a pulse's end is the timer's, lpc2148/valves.h).
 * `make rx-work` prints the figures and fails past the bounds below (the parse had moved
 * 30 135 bytes and summed 256 for a frame with a bad CRC: ~6 ms; BENCHMARKS.md, "Valve
 * firmware: work with interrupts off"). */
#include <stdio.h>
#include <string.h>
#include "../core/board.h"
#include "../core/crc16.h"
#include "../core/valvectl.h"

static unsigned long moved, summed;

void *__real_memmove(void *d, const void *s, size_t n);
void *__wrap_memmove(void *d, const void *s, size_t n)
{
    moved += n;
    return __real_memmove(d, s, n);
}

uint16_t __real_vc_crc16_update(uint16_t crc, const uint8_t *data, size_t n);
uint16_t __wrap_vc_crc16_update(uint16_t crc, const uint8_t *data, size_t n)
{
    summed += n;
    return __real_vc_crc16_update(crc, data, n);
}

void board_tx(const uint8_t *d, unsigned n) { (void)d; (void)n; }
void board_valve_pulse(unsigned v, uint16_t w, uint32_t t) { (void)v; (void)w; (void)t; }
void board_valves_off(void) {}
uint8_t board_outputs(void) { return 0; }
void board_note(int w, uint32_t a, uint32_t b) { (void)w; (void)a; (void)b; }
void board_stall(uint32_t ms) { (void)ms; }
uint32_t board_lock(void) { return 0; }
void board_unlock(uint32_t saved) { (void)saved; }

static vc_core core;

/* The work of the frame's last byte, the rest fed before. */
static int last_byte(const char *what, const uint8_t *f, unsigned n, unsigned long max_moved,
                     unsigned long max_summed)
{
    vc_rx(&core, f, n - 1u, 0);
    moved = summed = 0;
    vc_rx(&core, f + n - 1u, 1, 0);
    printf("%-34s last byte: %6lu bytes moved, %4lu bytes summed (bounds %lu, %lu)\n", what,
           moved, summed, max_moved, max_summed);
    return moved <= max_moved && summed <= max_summed;
}

int main(void)
{
    uint8_t f[247];
    unsigned i;
    uint16_t crc;
    int ok = 1;
    vc_init(&core, VC_RESET_POWER);
    f[0] = 0xA5; f[1] = 0x5A; f[2] = 240; f[3] = 0; f[4] = 0x11;   /* an unknown type */
    for (i = 5; i < 245; i++) f[i] = (uint8_t)(i * 7u + 3u) == 0xA5 ? 0 : (uint8_t)(i * 7u + 3u);
    crc = vc_crc16_update(0xFFFF, f + 2, 243);
    f[245] = (uint8_t)crc;
    f[246] = (uint8_t)((crc >> 8) ^ 1u);                             /* one bit wrong */
    ok &= last_byte("247-byte frame with a bad CRC", f, sizeof f, sizeof f, 32);
    f[246] = (uint8_t)(crc >> 8);
    ok &= last_byte("247-byte frame", f, sizeof f, 0, 32);           /* the reply's CRC */
    return ok ? 0 : 1;
}
