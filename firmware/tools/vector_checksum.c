/* Writes the LPC2148's vector checksum into a flash image (a .bin from address 0).
 *
 * The boot loader starts the user code only if the eight words of the exception vectors
 * (0x00..0x1C) add up to 0 (mod 2^32); the reserved vector at 0x14 holds the two's
 * complement of the other seven (UM10139, "Criterion for valid user code"). startup.S
 * leaves it 0: lpc21isp and Flash Magic patch it while they flash, but an image written by
 * other means (a JTAG probe, a programmer, a copy of the .bin) would not start. A host
 * tool, so the build needs no interpreter.  Usage: vector_checksum IMAGE.bin */
#include <stdint.h>
#include <stdio.h>

static uint32_t word(const unsigned char *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
           ((uint32_t)p[3] << 24);
}

int main(int argc, char **argv)
{
    unsigned char v[32];
    uint32_t sum = 0;
    unsigned k;
    FILE *f;
    if (argc != 2) {
        fprintf(stderr, "usage: %s IMAGE.bin\n", argv[0]);
        return 2;
    }
    f = fopen(argv[1], "r+b");
    if (!f || fread(v, 1, sizeof v, f) != sizeof v) {
        fprintf(stderr, "%s: cannot read its first 32 bytes (the vectors)\n", argv[1]);
        if (f) fclose(f);
        return 1;
    }
    for (k = 0; k < 8; k++)
        if (k != 5) sum += word(v + 4 * k);
    sum = 0u - sum;
    for (k = 0; k < 4; k++) v[20 + k] = (unsigned char)(sum >> (8 * k));
    if (fseek(f, 20, SEEK_SET) != 0 || fwrite(v + 20, 1, 4, f) != 4 || fclose(f) != 0) {
        fprintf(stderr, "%s: cannot write the checksum at 0x14\n", argv[1]);
        return 1;
    }
    printf("vector checksum 0x%08lx at 0x14 of %s\n", (unsigned long)sum, argv[1]);
    return 0;
}
