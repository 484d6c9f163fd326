#include "crc16.h"

uint16_t vc_crc16_byte(uint16_t crc, uint8_t b)
{
    int i;
    crc ^= (uint16_t)((uint16_t)b << 8);
    for (i = 0; i < 8; i++)
        crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
    return crc;
}

uint16_t vc_crc16_update(uint16_t crc, const uint8_t *data, size_t n)
{
    size_t i;
    for (i = 0; i < n; i++)
        crc = vc_crc16_byte(crc, data[i]);
    return crc;
}
